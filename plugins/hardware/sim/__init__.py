"""vistac built-in plugins."""
