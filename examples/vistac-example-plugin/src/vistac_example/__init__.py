"""Example vistac plugin package."""
