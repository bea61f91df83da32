"""Registers the dual filter and its process models. Imports nothing heavy."""

from __future__ import annotations

from vistac import hookimpl
from vistac.registry import Registry

_PACKAGE = "vistac.plugins.filters"


@hookimpl
def vistac_register(registry: Registry) -> None:
    registry.add("filter", "filters.dual", f"{_PACKAGE}.component:DualFilterComponent")
    registry.add("process_model", "filters.gnn", f"{_PACKAGE}.models:GNNProcessModel")
    registry.add("process_model", "filters.ff", f"{_PACKAGE}.models:FFProcessModel")
    registry.add("process_model", "filters.analytical", f"{_PACKAGE}.models:AnalyticalProcessModel")
