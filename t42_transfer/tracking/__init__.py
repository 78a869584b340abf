"""Seeing the object: fiducial-marker tracking (:mod:`.markers`) and a simulated camera (:mod:`.render`).

Nothing here needs ROS.  The submodules import OpenCV and MuJoCo's renderer, so this package imports
neither: only code that tracks or renders pays for them.
"""
