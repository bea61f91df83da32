"""RGB-D cameras: a live OpenCV camera and a replay of recorded frames."""
