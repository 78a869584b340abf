"""The real hand's hardware: the XM430 servos' control table, and an emulated servo bus that speaks their protocol.

:mod:`.xm430` holds the facts of the servo (addresses, sizes, units, error bits) once, for the emulator and
the driver alike; :mod:`.protocol` is the servo's side of Dynamixel protocol 2.0 (the driver speaks it through
dynamixel-sdk); :mod:`.emulator` puts two emulated servos on a pseudo-terminal, behind which a plant (the
simulated hand) moves.
"""
