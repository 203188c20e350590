"""Typed params: constraints declared on dataclass fields, checked when read from a file and when built in code."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

import pytest

from rover.pipeline import params as P
from rover.pipeline.params import Checked, Matches, ParamTypeError, ParamValueError, PositiveFloat, Range


@dataclass(frozen=True)
class Example(Checked):
    rate_hz: PositiveFloat = 1.0
    window: Annotated[int, Range(ge=2, le=10)] = 3
    limit_s: PositiveFloat | None = None
    speed: Literal["max"] | PositiveFloat = "max"
    pair: tuple[float, float] = (0.0, 1.0)
    name: Annotated[str, Matches(r"[a-z]+", "lower-case letters")] = "ok"


def hints() -> dict:
    return P.resolved_types(Example)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("rate_hz", 0, "must be > 0, got 0"),
        ("rate_hz", float("nan"), "expected a finite number"),
        ("rate_hz", float("inf"), "expected a finite number"),
        # the words Python's float() reads as infinite or not a number, as a command line gives them
        ("rate_hz", "inf", "expected a finite number, got 'inf'"),
        ("rate_hz", "-Infinity", "expected a finite number, got '-Infinity'"),
        ("rate_hz", "nan", "expected a finite number, got 'nan'"),
        ("window", 11, "must be >= 2 and <= 10, got 11"),
        ("window", 2.5, "expected int"),
        ("limit_s", -1.0, "expected float > 0 | null"),
        ("speed", -1, "expected 'max' | float > 0, got -1"),
        ("name", "Bad", "expected lower-case letters, got 'Bad'"),
    ],
)
def test_coerce_rejects_values_outside_the_declared_rules(field, value, message):
    with pytest.raises(ParamTypeError, match=message.replace("|", r"\|")):
        P.coerce(value, hints()[field])


def test_coerce_accepts_and_widens():
    assert P.coerce(2, hints()["rate_hz"]) == 2.0 and isinstance(P.coerce(2, hints()["rate_hz"]), float)
    assert P.coerce(None, hints()["limit_s"]) is None
    assert P.coerce("max", hints()["speed"]) == "max"
    assert P.coerce([1, 2], hints()["pair"]) == (1.0, 2.0)


def test_labels_show_the_rules():
    assert P.type_label(hints()["window"]) == "int >= 2 and <= 10"
    assert P.type_label(hints()["speed"]) == "'max' | float > 0"


def test_objects_built_in_code_obey_the_same_rules():
    assert Example(limit_s=2.0, speed=3.0).limit_s == 2.0
    with pytest.raises(ParamValueError, match="rate_hz: must be > 0") as info:
        Example(rate_hz=-1.0)
    assert info.value.name == "rate_hz"
    with pytest.raises(ParamValueError, match="limit_s: expected a finite number"):
        Example(limit_s=float("nan"))
    with pytest.raises(ParamValueError, match="speed: must be > 0"):
        Example(speed=0.0)


def test_bind_reports_each_problem_at_its_key():
    found: list[tuple[tuple, str]] = []
    wording = P.Wording(unknown=lambda k: f"unknown {k}", ill_typed=lambda k: f"bad {k}", missing=lambda k, t: k)
    assert (
        P.bind(Example, {"rate_hz": 0, "window": 1, "nme": "x"}, wording, lambda p, m, _k: found.append((p, m))) is None
    )
    assert (("rate_hz",), "bad rate_hz: must be > 0, got 0.0") in found
    assert (("window",), "bad window: must be >= 2 and <= 10, got 1") in found
    assert any(p == ("nme",) and "did you mean 'name'" in m for p, m in found)


def test_fixed_length_tuples_check_their_length():
    with pytest.raises(ParamTypeError, match=r"\(2 values\)"):
        P.coerce([1.0, 2.0, 3.0], hints()["pair"])
    assert P.coerce([1, 2], tuple[int, ...]) == (1, 2)
