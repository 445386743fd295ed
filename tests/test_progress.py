"""Issue 28, item 2: progress that tells the truth. The fraction (forward only, set-up included, the end at 1), the
time left (from measured phase times, "estimating" until it can be), one loss scale, counters named as the panel
names them, the count of stylized splats, and view selection's report per camera. The model on a simulated clock,
then real runs of a tiny scene through the engine's progress callback."""

import math
import time

import numpy as np
import pytest
from test_pipeline import TINY, ring_cameras, run, sphere_scene

from dresg_addon.method.bookkeeping import Progress, ProgressLines, ProgressModel, format_seconds
from dresg_addon.method.color_solve import FIT_SOLVE
from dresg_addon.method.views import select_active_views

# --- the model on a simulated clock ----------------------------------------------------------------------------


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def simulate(model: ProgressModel, clock: Clock, stages_run: int, stages: int, slow_stage: int = 0, post=True):
    """A run of 4 cameras, 3 views, ``stages_run`` of ``stages`` stages (then the post stage) on ``clock``: 1 s a
    camera, a set-up step, a view's proposal, a solve round, a feedback; stage ``slow_stage`` 10x slower. Returns
    (seconds, fraction, seconds left or None) of each report."""
    reports = []

    def report(phase, stage, step, steps, seconds):
        fraction, left = model.update(phase, stage, step, steps)
        reports.append((clock.now, fraction, left))
        clock.now += seconds

    model.plan(stages, post)
    model.set_counts(cameras=4, views=3)
    for camera in range(5):
        report("select", 0, camera, 4, 1.0 if camera < 4 else 0.0)
    for step in range(6):
        report("setup", 0, step, 6, 1.0)
    for stage in range(1, stages_run + 1):
        slow = 10.0 if stage == slow_stage else 1.0
        for view in range(3):
            report("proposal", stage, view, 3, slow)
        for step in range(3):
            report("fit", stage, step, 3, slow)
        report("fit", stage, 3, 3, 0.0)
        report("feedback", stage, 0, 1, slow)
    if post:
        for step in range(3):
            report("post", stages + 1, step, 3, 1.0)
    report("done", 0, 1, 1, 0.0)
    return reports


def test_the_fraction_moves_forward_to_1_and_the_time_left_is_exact_once_a_stage_is_timed():
    clock = Clock()
    reports = simulate(ProgressModel(clock), clock, stages_run=4, stages=4)
    fractions = [fraction for _, fraction, _ in reports]
    assert all(b >= a for a, b in zip(fractions, fractions[1:]))
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    total = reports[-1][0]
    # Set-up gets its share of the bar: 4 s of selection and 6 s of set-up of the 10 + 4 x 7 + 3 = 41 s.
    after_setup = next(f for t, f, _ in reports if t >= 10.0)
    assert 0.1 < after_setup < 0.4
    # "Estimating" (None) until the view selection has ended (after 4 s), then priced by its seconds per unit of
    # cost; once the first stage has ended (after 10 + 7 s) the exact end: every phase costs what its first one did.
    first = next(i for i, (_, _, left) in enumerate(reports) if left is not None)
    assert reports[first][0] == pytest.approx(4.0)
    for now, _, left in reports[first:]:
        assert left >= 0 and (now < 17.0 or now + left == pytest.approx(total))


def test_an_early_stop_jumps_the_bar_forward_and_a_slow_stage_never_moves_it_back():
    clock = Clock()
    reports = simulate(ProgressModel(clock), clock, stages_run=2, stages=6, slow_stage=2)
    fractions = [fraction for _, fraction, _ in reports]
    assert all(b >= a for a, b in zip(fractions, fractions[1:]))
    assert fractions[-1] == 1.0
    # The post stage follows stage 2 of 6: the bar jumps over the four stages left out.
    post = next(i for i, (now, _, _) in enumerate(reports) if now >= reports[-1][0] - 3.0)
    assert fractions[post] - fractions[post - 1] > 0.3
    # The estimate counts every stage (an upper bound when the stages stop early) and follows the slow stage.
    lefts = [(now, left) for now, _, left in reports if left is not None]
    assert lefts and all(left >= 0 for _, left in lefts)


def test_a_resumed_run_estimates_from_the_stages_in_its_checkpoint():
    clock = Clock()
    model = ProgressModel(clock)
    model.plan(3, False)
    model.first_stage = 3
    model.update("setup", 0, 0, 1)
    clock.now = 5.0
    assert model.update("proposal", 3, 0, 2)[1] is not None  # the set-up timed: priced from it
    for stage in (1, 2):
        model.adopt({"stage": stage, "proposal_seconds": 2.0, "stage_seconds": 5.0, "feedback_seconds": 1.0})
    fraction, left = model.update("proposal", 3, 1, 2)
    assert left == pytest.approx(2.0 + 3.0 + 1.0)  # this stage's proposals (none of its 2 s spent yet), fit, feedback
    assert 0 < fraction < 1


def test_the_text_names_the_stage_its_counter_the_rmse_and_the_time_left():
    p = Progress(2, 6, 3, 6, "fit", 0.04271, 65.0, "colour solve round 3 (at most 6)", 0.4)
    assert p.text() == "Stage 2/6 | colour solve round 3 (at most 6) | fit RMSE 0.0427 | 1m 05s left"
    p = Progress(0, 6, 3, 16, "select", math.nan, math.nan, "selecting views: 3/16 cameras rendered", 0.05)
    assert p.text() == "selecting views: 3/16 cameras rendered | estimating time left"
    assert Progress(7, 6, 1, 6, "post", 0.05, 3.0, "colour solve round 1 (at most 6)").text().startswith("Final")
    assert format_seconds(3725) == "1h 02m" and format_seconds(math.nan) == "?"
    lines, now = ProgressLines(2.0, clock=lambda: now), 0.0
    assert lines.line(p) is not None and lines.line(p) is None  # the same phase within 2 s: not printed again
    now = 2.5
    assert lines.line(p) is not None


# --- real runs -----------------------------------------------------------------------------------------------


def _timed_run(config, **kwargs):
    """A run with every report and the time since the start of stylize when it came; the result and its time."""
    reports = []
    started = time.perf_counter()
    result = run(config=config, progress=lambda p: reports.append((time.perf_counter() - started, p)), **kwargs)
    return reports, result, time.perf_counter() - started


def test_a_stylization_reports_a_rising_fraction_one_loss_scale_and_estimates_near_its_time():
    """The engine's callback on a tiny run of 4 stages (no early stop): the fraction never decreases and ends at 1;
    "estimating" until the view selection has ended (the first part timed), then each estimate of the end within 3x of the run's time (2x is
    the aim: tiny runs' phases take milliseconds, so the bound is generous), 5x while the set-up is priced by the view
    selection alone (its first 0.3 s: beside another job on 2 cores, load 4, 4.1x); every loss on the fit RMSE's
    scale."""
    config = TINY.with_(stages=4, early_stop=0.0)
    scene, cameras = sphere_scene(2000), ring_cameras(4, 96, 64)
    reports, result, seconds = _timed_run(config, scene=scene, cameras=cameras)
    fractions = [p.fraction for _, p in reports]
    assert all(b >= a for a, b in zip(fractions, fractions[1:])), fractions
    assert fractions[-1] == 1.0 and reports[-1][1].phase == "done"
    assert sum(p.phase == "select" for _, p in reports) == len(cameras) + 1  # the start, then one per camera
    assert max(p.fraction for _, p in reports if p.stage == 0) > 0.05  # view selection and set-up have a share
    estimated = [(now, p) for now, p in reports if math.isfinite(p.eta_seconds)]
    first = reports.index(next(r for r in reports if math.isfinite(r[1].eta_seconds)))
    assert all("estimating time left" in p.text() for _, p in reports[:first])
    assert reports[first][1].phase == "setup"  # once the view selection has ended: priced by its seconds per unit
    for now, p in estimated:
        bound = 5 if p.phase == "setup" else 3
        assert seconds / bound <= now + p.eta_seconds <= bound * seconds, (now, p.eta_seconds, seconds, p.text())
    # One scale: the fit's RMSE over covered pixels, the last one the log's.
    losses = [p.loss for _, p in reports if math.isfinite(p.loss)]
    assert losses and all(0 <= loss < 1 for loss in losses)
    assert reports[-1][1].loss == pytest.approx(result.log[-1]["fit_residual"])
    for entry in result.log[:-1]:  # each fit's end reports the log's fit residual
        ends = [p for _, p in reports if p.phase == "fit" and p.stage == entry["stage"] and p.step == p.steps]
        assert ends[-1].loss == pytest.approx(entry["fit_residual"])


@pytest.mark.parametrize("color_fit", ["solve", "adam"])
def test_the_fit_counter_names_rounds_or_steps_as_the_settings_do(color_fit):
    config = TINY.with_(stages=1, optimize_geometry=color_fit == "adam", fit_steps=3, post_steps=2)
    reports, _, _ = _timed_run(config)
    fits = [p for _, p in reports if p.phase == "fit" and p.step > 0]
    posts = [p for _, p in reports if p.phase == "post" and p.step > 0]
    if color_fit == "solve":
        assert all(p.message.startswith("colour solve round ") for p in fits + posts)
        assert all(p.message.endswith(f"(at most {FIT_SOLVE.max_rounds})") for p in fits + posts)
    else:  # geometry offsets: the plan's Adam steps
        assert [p.message for p in fits] == ["fit step 1/3", "fit step 2/3", "fit step 3/3"]
        assert [p.message for p in posts] == ["fit step 1/2", "fit step 2/2"]
        assert all(0 <= p.loss < 1 for p in fits + posts)


def test_the_result_counts_the_splats_it_stylized():
    """The splats the run fitted: those an active view sees, of the selection when there is one (the Blender report
    and the command line's summary say this count)."""
    scene = sphere_scene(400, far=50)
    everything = run(scene=scene)
    assert 300 < everything.stylized <= 400  # the far splats no view sees are left out
    assert everything.stylized == everything.log[0]["gaussians_optimised"]
    mask = np.zeros(len(scene), bool)
    mask[:150] = True
    mask[-10:] = True  # 10 of them out of every view
    selected = run(scene=scene, mask=mask)
    assert 100 < selected.stylized <= 150 and selected.stylized == selected.log[0]["gaussians_optimised"]
    changed = np.abs(selected.scene.sh_dc - scene.sh_dc).max(1) > 0
    assert not changed[~mask].any() and 0.9 * selected.stylized <= changed.sum() <= selected.stylized


def test_view_selection_reports_once_per_camera():
    cameras = ring_cameras(5)
    calls = []
    select_active_views(sphere_scene(), cameras, TINY.config, progress=lambda done, total: calls.append((done, total)))
    assert calls == [(k, 5) for k in range(1, 6)]


def test_the_fits_prior_cost_counts_what_the_fit_runs():
    """Before a stage is timed the bar prices a fit by what it runs: a solve, a solve with each view solved alone
    (the best views), or Adam steps with a render per step."""
    from dresg_addon.method.backends import BACKENDS
    from dresg_addon.method.bookkeeping import BEST_VIEWS_FIT_COST, PRIOR_COSTS, prior_costs
    from dresg_addon.method.config import preset_run

    def fit_cost(name, **changes):
        config, plan = preset_run(name, **changes)
        return prior_costs(config, plan, BACKENDS[config.proposal])["fit"]

    assert fit_cost("cpu") == PRIOR_COSTS["fit"]
    assert fit_cost("standard", best_views_coarse=True) == pytest.approx(PRIOR_COSTS["fit"] * BEST_VIEWS_FIT_COST)
    assert fit_cost("standard") == PRIOR_COSTS["fit"]  # only its full-detail stages' fits: priced stage by stage
    assert fit_cost("standard", best_views=0.0) == PRIOR_COSTS["fit"]
    assert fit_cost("paper") == pytest.approx(0.8 * preset_run("paper")[1].fit_steps)
    config, plan = preset_run("paper", proposal="sd15")
    assert prior_costs(config, plan, BACKENDS["sd15"])["proposal"] == BACKENDS["sd15"].proposal_cost * 10


def test_stages_not_run_yet_are_priced_by_their_own_cost():
    """A coarse-to-fine backend's full-resolution stages cost more than its coarse ones (relative_cost): once
    stages 1 and 2 (cost 1 each) took 2 s of proposals each, stage 3 (cost 3) is expected to take 6 s."""
    clock = Clock()
    model = ProgressModel(clock)
    model.plan(3, False)
    model.set_counts(cameras=0, views=1)
    model.set_stage_costs([1.0, 1.0, 3.0])
    assert model.weight("proposal", 3) == pytest.approx(3 * model.weight("proposal", 1))  # priced before any ran
    for stage in (1, 2):
        model.timed[("proposal", stage)] = 2.0
    assert model.weight("proposal", 3) == pytest.approx(6.0)
    model.set_stage_costs([1.0, float("nan"), 0.0])  # unusable costs are left out: the stages' mean
    assert model.weight("proposal", 3) == pytest.approx(2.0)


def test_a_fit_with_the_best_views_is_priced_above_a_joint_one_before_it_runs():
    """standard's coarse stages take the joint fit, its full-detail ones the best views (BEST_VIEWS_STAGE_FIT_COST): once
    two joint fits took 3 s each, a best-views fit is expected to take 3 x that cost; before any fit, the joint
    fit's prior x its cost."""
    from dresg_addon.method.bookkeeping import BEST_VIEWS_STAGE_FIT_COST, PRIOR_COSTS

    model = ProgressModel(Clock())
    model.plan(3, False)
    model.set_counts(cameras=0, views=2)
    model.set_stage_costs([1.0, 1.0, BEST_VIEWS_STAGE_FIT_COST], "fit")
    model.timed[("select", 0)] = 2.0 * PRIOR_COSTS["select"]  # two units' priors take 2 s: a second a unit
    assert model.weight("fit", 3) == pytest.approx(BEST_VIEWS_STAGE_FIT_COST * model.weight("fit", 1))
    assert model.weight("fit", 1) == pytest.approx(2 * PRIOR_COSTS["fit"])
    for stage in (1, 2):
        model.timed[("fit", stage)] = 3.0
    assert model.weight("fit", 3) == pytest.approx(3.0 * BEST_VIEWS_STAGE_FIT_COST)
    assert model.weight("proposal", 3) == model.weight("proposal", 1)  # the proposals' costs are their own


def test_later_fits_and_a_stages_marks_are_priced_from_the_first_fit_by_their_costs():
    """The first solve costs FIRST_FIT_COST of a later coarse one (it starts from the capture's colours): once it took
    1.4 x 10 s, a coarse fit is expected to take 10 s, a best-views one 15 s, and a stage's marks, priced like a
    coarse fit (not the mean of the fits that ran), 10 s x their prior over the fit's."""
    from dresg_addon.method.bookkeeping import BEST_VIEWS_STAGE_FIT_COST, FIRST_FIT_COST, PRIOR_COSTS

    model = ProgressModel(Clock())
    model.plan(3, False)
    model.set_counts(cameras=0, views=2)
    model.set_stage_costs([FIRST_FIT_COST, 1.0, BEST_VIEWS_STAGE_FIT_COST], "fit")
    model.set_marks_stages([3])
    model.timed[("fit", 1)] = FIRST_FIT_COST * 10.0
    assert model.weight("fit", 2) == pytest.approx(10.0)
    assert model.weight("fit", 3) == pytest.approx(10.0 * BEST_VIEWS_STAGE_FIT_COST)
    assert model.weight("marks", 3) == pytest.approx(10.0 * PRIOR_COSTS["marks"] / PRIOR_COSTS["fit"])


def test_the_synth_backend_prices_its_full_resolution_stages_above_its_coarse_ones():
    from dresg_addon.method.proposal.synth import SynthBackend
    from dresg_addon.method.schedule import stage_timesteps

    backend = SynthBackend()
    costs = [backend.relative_cost(stage, 320, 448) for stage in stage_timesteps(12, 1)]
    assert all(math.isfinite(c) and c > 0 for c in costs) and costs == sorted(costs)
    assert costs[-1] == pytest.approx(1.35 * costs[0], rel=0.05)  # 1.28-1.48x, measured


def test_the_time_left_expects_the_early_stop_and_prices_the_marks_of_the_stages_that_carry_them():
    """A run of 6 stages that may stop after stage 4 (the first at full detail), whose stages 4 on carry marks: 1 s a
    camera, a view's proposal, a solve round; 3 s for a stage's marks. Stopped after 4, the estimate from stage 2 on
    is within 1.25x of the truth; going on, each further stage is counted as it starts."""
    clock, reports = Clock(), []
    model = ProgressModel(clock)

    def report(phase, stage, step, steps, seconds):
        fraction, left = model.update(phase, stage, step, steps)
        reports.append((phase, stage, step, clock.now, left))
        clock.now += seconds

    model.plan(6, False)
    model.set_counts(cameras=3, views=3)
    model.set_marks_stages([4, 5, 6])
    model.expect_stop(4)
    for camera in range(4):
        report("select", 0, camera, 3, 1.0 if camera < 3 else 0.0)
    report("setup", 0, 0, 1, 3.0)
    for stage in range(1, 5):
        for view in range(3):
            report("proposal", stage, view, 3, 1.0)
        if stage >= 4:
            report("marks", stage, 0, 1, 3.0)
        report("fit", stage, 0, 1, 3.0)
        report("feedback", stage, 0, 1, 1.0)
    report("done", 0, 1, 1, 0.0)
    total = reports[-1][3]
    for phase, stage, step, now, left in reports:
        if phase == "proposal" and step == 0 and stage >= 2:
            assert 1 / 1.25 <= left / (total - now) <= 1.25, (stage, left, total - now)
    # Past the expected stop, the stage it goes on to counts, with its marks; the ones after it do not yet.
    going_on = ProgressModel(Clock())
    going_on.plan(6, False)
    going_on.set_marks_stages([4, 5, 6])
    going_on.expect_stop(4)
    assert ("feedback", 4) in going_on.parts() and ("proposal", 5) not in going_on.parts()
    going_on.update("proposal", 5, 0, 3)
    parts = going_on.parts()
    assert ("proposal", 5) in parts and ("marks", 5) in parts and ("proposal", 6) not in parts
    assert ("marks", 3) not in parts
