"""ROS nodes over a :class:`~t42_transfer.ros.transport.Transport`: thin wiring of topics to plain modules.

Nodes hold no science and convert messages only through :mod:`msg_adapters`.
"""
