"""EKF-SLAM for a UAV's return to base without GNSS (Lee and Tahk 2010, issue 14).

Plain numpy, no I/O: :mod:`.model` (motion and range/azimuth/elevation observation models with
their Jacobians), :mod:`.filter` (:class:`EkfSlam`: prediction, Joseph-form update, augmentation,
gating, sub-maps, first-estimates Jacobians), :mod:`.planner` (:class:`RecoveryPlanner`, the
seed's STEPs 1-6 as a state machine), :mod:`.config` (the settings dataclasses).

Frames everywhere: MAVLink LOCAL_NED (north, east, down; metres), yaw clockwise from north
(radians). The seed's x, y, psi are north, east, yaw (its ``tan^-1(y/x)`` is
``atan2(east, north)``); its altitude is up, so the vehicle is at down = -altitude.
"""
