"""Every numerical-stability case of dresg_addon.evaluation.stability runs as a test: finite and bounded results."""

from __future__ import annotations

import math

import pytest

from dresg_addon.evaluation import stability

KNOWN_FAILURES: dict[str, str] = {}  # case function name -> reason, run as a strict xfail


def _params():
    for case in stability.CASES:
        reason = KNOWN_FAILURES.get(case.__name__)
        marks = [pytest.mark.xfail(strict=True, reason=reason)] if reason else []
        yield pytest.param(case, id=case.__name__.removeprefix("case_"), marks=marks)


@pytest.mark.parametrize("case", list(_params()))
def test_case(case):
    result = stability.run_case(case)
    assert not result.error, result.error
    assert result.checked and result.stages and result.observed
    numbers = {k: v for k, v in result.observed.items() if isinstance(v, float | int) and not isinstance(v, bool)}
    assert numbers, "a case must report measured values"
    assert all(math.isfinite(v) for v in numbers.values()), result.observed
    assert result.passed, stability.format_markdown([result])


def test_a_case_that_raises_is_reported_as_failed():
    def case_broken():
        """Divides by zero."""
        return 1 / 0

    result = stability.run_case(case_broken)
    assert not result.passed
    assert result.name == "broken" and "ZeroDivisionError" in result.error
    table = stability.format_markdown([result])
    assert "**FAIL**" in table and "ZeroDivisionError" in table and "0 of 1 cases passed" in table


def test_non_finite_observations_fail_a_case():
    result = stability._result("x", "stage", "checked", {"value": float("nan"), "fine": 1.0}, True)
    assert not result.passed and result.non_finite() == ["value"]


def test_scaled_scene_keeps_the_image():
    scene, cameras = stability.tiny_scene(8), stability.tiny_cameras()
    big, big_cameras = stability.scaled_scene(scene, cameras, 100.0)
    assert big.means == pytest.approx(scene.means * 100.0, rel=1e-6)
    assert big_cameras[1].center == pytest.approx(cameras[1].center * 100.0, rel=1e-9)
    assert big_cameras[0].fx == cameras[0].fx
