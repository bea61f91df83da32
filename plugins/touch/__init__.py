"""Touch-only recognition, 6D pose estimation and shape learning (paper 2)."""
