"""The controllers and their kinds' registry: a kind is one file and one line below."""

from . import fosmc, smc, super_twisting
from .kind import KINDS, SPACES, Kind, Param, Space, register

register(fosmc.KIND)
register(smc.KIND)
register(super_twisting.KIND)

__all__ = ["KINDS", "SPACES", "Kind", "Param", "Space", "register"]
