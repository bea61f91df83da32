"""Robotiq 2F-85 gripper (Modbus RTU over serial, or the UR gripper socket)."""
