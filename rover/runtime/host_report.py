"""What a host tells the others of its operators once its part of a run is done: what each
received, sent and dropped, and where its time went, so that every host's run.json describes the
whole run (worker processes above all: one run, several processes).

A report is JSON, put once on the host's presence keys (`.../report`, rover/transport/keys.py)
before its `done` token. It comes from a host of the same run (its digest checked, and its
certificate when the pipeline has `security:`), but it is still read as untrusted input: anything
not of the shape written here is ReportError, and the report is left out.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from typing import Any

from rover.operator import OperatorCounts, OperatorProfile

PROFILE_FIELDS = tuple(f.name for f in dataclasses.fields(OperatorProfile))
COUNT_FIELDS = ("received", "sent", "dropped")


class ReportError(ValueError):
    """A report that is not what `encode` writes; the message names the part."""


@dataclasses.dataclass(frozen=True)
class HostReport:
    """One host's operators: their counts and profiles, by operator name."""

    counts: Mapping[str, OperatorCounts]
    profile: Mapping[str, OperatorProfile]


def encode(report: HostReport) -> bytes:
    doc = {
        name: {
            "counts": {f: dict(getattr(report.counts[name], f)) for f in COUNT_FIELDS},
            "profile": dataclasses.asdict(report.profile[name]) if name in report.profile else None,
        }
        for name in sorted(report.counts)
    }
    return json.dumps(doc, sort_keys=True).encode()


def decode(payload: bytes) -> HostReport:
    """The report `encode` wrote; ReportError naming what is wrong otherwise."""
    try:
        doc = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ReportError(f"not UTF-8 JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ReportError("not a JSON object of operators")
    counts: dict[str, OperatorCounts] = {}
    profile: dict[str, OperatorProfile] = {}
    for name, entry in doc.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("counts"), dict):
            raise ReportError(f"operator {name!r}: no counts")
        counts[name] = OperatorCounts(*(_tally(entry["counts"].get(f), f"{name}.{f}") for f in COUNT_FIELDS))
        if entry.get("profile") is not None:
            profile[name] = _profile(entry["profile"], name)
    return HostReport(counts, profile)


def _tally(value: Any, where: str) -> dict[str, int]:
    if not isinstance(value, dict) or not all(
        isinstance(k, str) and isinstance(v, int) and not isinstance(v, bool) and v >= 0 for k, v in value.items()
    ):
        raise ReportError(f"{where}: expected counts by name (whole numbers of at least 0)")
    return dict(value)


def _profile(value: Any, name: str) -> OperatorProfile:
    if not isinstance(value, dict) or set(value) != set(PROFILE_FIELDS):
        raise ReportError(f"operator {name!r}: a profile has the fields {', '.join(PROFILE_FIELDS)}")
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 for v in value.values()):
        raise ReportError(f"operator {name!r}: profile times are seconds of at least 0")
    return OperatorProfile(**{k: float(v) for k, v in value.items()})
