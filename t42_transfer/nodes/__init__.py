"""The suite's rclpy nodes: thin wiring of topics, services and parameters to plain modules.

Nodes hold no science and convert messages only through :mod:`msg_adapters`;
:mod:`t42_transfer.nodes.registry` lists the runnable ones.
"""
