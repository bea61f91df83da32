"""Shape perception plugins."""
