"""Built-in behaviours: the skill vocabulary of the YAML tree."""
