"""Generic CAN force/tactile sensor through python-can."""
