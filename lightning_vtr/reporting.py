"""Deprecated: moved to :mod:`lightning_vtr.evaluation.tables` in 0.2 (this alias goes in 0.3)."""

from lightning_vtr.utils.deprecation import alias_module

alias_module(__name__, "lightning_vtr.evaluation.tables")
