"""Contactile PapillArray tactile pads over their USB serial stream."""
