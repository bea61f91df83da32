"""Protocol-level emulators of the real devices (UR controller, Robotiq, PapillArray)."""
