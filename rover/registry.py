"""Finding operator classes: built-ins by short name, user classes by dotted path."""

from __future__ import annotations

import importlib

from rover.errors import OperatorDefinitionError
from rover.operator import Operator

BUILTINS: dict[str, str] = {
    "dataset_replay": "rover.drivers.replay:DatasetReplay",
    "channel_sweep": "rover.operators.channel_sweep:ChannelSweep",
    "csi_decode": "rover.operators.csi_decode:CsiDecode",
    "aoa": "rover.operators.aoa:Aoa",
    "preintegration": "rover.operators.preintegration:Preintegration",
    "slam": "rover.operators.slam:Slam",
    "channel_hop": "rover.drivers.channel_hop:ChannelHop",
    "csi_netlink": "rover.drivers.csi_netlink:CsiNetlink",
    "csi_file": "rover.drivers.csi_file:CsiFile",
    "recorder": "rover.drivers.recorder:Recorder",
    "run_outputs": "rover.drivers.run_outputs:RunOutputs",
}
"""Short name -> `module:Class`; modules are imported only when a pipeline uses them."""


class UnknownOperator(LookupError):
    """`uses:` names neither a built-in nor an importable Operator class."""


def resolve(uses: str) -> type[Operator]:
    """The Operator class for a `uses:` value; raise UnknownOperator with the reason."""
    if uses in BUILTINS:
        module_name, _, attr = BUILTINS[uses].partition(":")
    elif "." in uses:
        module_name, _, attr = uses.rpartition(".")
    else:
        raise UnknownOperator(f"unknown operator {uses!r}")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise UnknownOperator(f"cannot import {module_name!r} for operator {uses!r}: {exc}") from None
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, Operator)):
        raise UnknownOperator(f"{uses!r} is not an Operator class")
    try:
        cls.check_definition()
    except OperatorDefinitionError as exc:
        raise UnknownOperator(f"operator {uses!r} is badly declared: {exc}") from None
    return cls
