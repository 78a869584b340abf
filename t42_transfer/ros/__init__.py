"""ROS 2 (Jazzy) wire conventions and the transport interface nodes are written against.

``naming`` and ``qos`` are pure; ``transport`` holds the abstract :class:`Transport`
and the one CDR (de)serialisation helper; ``inprocess`` is a backend for unit tests.
"""
