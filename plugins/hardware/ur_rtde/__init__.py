"""UR arm over RTDE (the ``ur_rtde`` package)."""
