"""What ``t42 view`` shows: the scene as plain data (scene.py), a matplotlib picture of it (snapshot.py), and the
Foxglove WebSocket servers of a live graph (the ``view`` node) and of a recorded bag (bag_server.py).

No ROS and no torch in scene.py and snapshot.py: reports and tests draw scenes without a graph.
"""
