"""Dual differentiable filter: state layout, process models and the filter."""
