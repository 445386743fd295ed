"""Issue 28, item 2, in the bpy module: the Blender job's bar and time left as its poll loop shows them, the report
that counts the splats a selection run stylized, and Select Views by Coverage reporting each camera."""

import math
import re
import time

import numpy as np
import pytest
from test_blender_artist import _import, _scene

from dresg_addon.util.imageio import write_image

bpy = pytest.importorskip("bpy")
pytest.importorskip("torch")
pytestmark = pytest.mark.blender


def _style(tmp_path) -> str:
    noise = np.random.default_rng(3).uniform(-0.1, 0.1, (24, 32, 3))
    write_image(tmp_path / "style.png", np.clip(np.float32([0.9, 0.2, 0.1]) + noise, 0, 1).astype(np.float32))
    return str(tmp_path / "style.png")


def test_the_poll_loop_shows_a_rising_bar_and_estimates_near_the_runs_time(addon, tmp_path):
    """A run on a worker thread, read the way the panel reads it (the job's fraction, text and eta after each poll):
    the bar never goes back and ends at 1; the text says "estimating" until the view selection has ended; from then on
    each estimate of the end (time so far + time left) is within 3x of the run's time (2x is the aim; a tiny
    scene's phases take milliseconds, so the bound is generous)."""
    ops = addon.operators
    obj = _import(tmp_path, _scene(n=3000, spread=0.5))
    splats = ops.splat_object.scene_from_object(obj)
    config, plan = addon.dresg_addon.method.config.preset_run(
        "preview", stages=4, early_stop=0.0, proposal_width=32, proposal_height=24, max_views=3
    )
    from stylize_gaussians.dresg_addon.scene.orbit import orbit_cameras

    cameras = orbit_cameras(splats, 4, width=96, height=64)
    style = np.random.default_rng(1).uniform(size=(24, 32, 3)).astype(np.float32)
    run = ops.job.StylizeJob(obj, splats, cameras, style, config, plan=plan)
    seen = []  # (seconds since the start, fraction, eta, text) after each poll
    started = time.monotonic()
    run.start()
    deadline = started + 300
    while time.monotonic() < deadline:
        ended = run.poll()
        seen.append((time.monotonic() - started, run.fraction, run.eta, run.text))
        if ended:
            break
        time.sleep(0.005)
    assert run.state is ops.tasks.JobState.DONE, run.error
    seconds = run.seconds
    fractions = [fraction for _, fraction, _, _ in seen]
    assert all(b >= a for a, b in zip(fractions, fractions[1:])), fractions
    assert fractions[-1] == 1.0 and run.text.startswith("Done in")
    assert any(0 < f < 1 and "set-up" in text for _, f, _, text in seen)  # the set-up has its share and a label
    estimates = [(now, eta, text) for now, _, eta, text in seen if eta is not None]
    assert len(estimates) > 1, "no estimate shown before the end"
    first = next(i for i, (_, _, eta, _) in enumerate(seen) if eta is not None)
    assert all("estimating time left" in text for _, f, _, text in seen[:first] if f > 0)
    assert seen[first][3].startswith("set-up: "), seen[first][3]  # once the view selection has ended
    for now, eta, text in estimates:
        assert seconds / 3 <= now + eta <= 3 * seconds, (now, eta, seconds, text)
    losses = [float(m) for *_, text in seen for m in re.findall(r"fit RMSE ([0-9.]+)", text)]
    assert losses and all(loss < 1 for loss in losses)


@pytest.mark.slow
def test_the_report_after_a_selection_run_counts_the_selection(addon, tmp_path, capfd):
    obj = _import(tmp_path, _scene(n=300, spread=0.5))
    bpy.ops.dresg.add_orbit_cameras(count=3)
    settings = bpy.context.scene.dresg
    for name, value in {"stages": 1, "proposal_width": 32, "proposal_height": 24}.items():
        setattr(settings, name, value)
    settings.preset, settings.max_views, settings.style_path = "preview", 3, _style(tmp_path)
    left = np.array([v.co.x for v in obj.data.vertices]) < 0
    obj.data.vertices.foreach_set("select", left)
    settings.selection = "SELECTED"
    capfd.readouterr()
    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    run = addon.operators.job.StylizeJob.current()
    assert run.n_selected == left.sum() and run.n_fitted is not None
    assert 0.9 * left.sum() <= run.n_fitted <= left.sum() and 0 < run.n_changed <= run.n_fitted
    if run.n_changed == left.sum():
        assert run.summary().startswith(f"Stylized {left.sum():,} selected splats in ")
    else:  # the count is of the splats whose colours changed
        assert run.summary().startswith(f"Stylized {run.n_changed:,} of the {left.sum():,} selected splats in ")
    assert f"{len(left)} splats" not in run.summary()
    out = capfd.readouterr().out
    assert run.summary() in out  # the operator's report, as Blender prints it in background mode
    assert re.search(r"\[stylize\]\s+\d+% set-up: ", out)  # the set-up's lines, with the bar's fraction

    settings.selection = "ALL"
    assert bpy.ops.dresg.stylize() == {"FINISHED"}
    everything = addon.operators.job.StylizeJob.current()
    assert everything.n_selected == len(left) and everything.summary().startswith("Stylized ")
    assert "selected" not in everything.summary()


def test_select_views_reports_each_camera(addon, tmp_path, capfd):
    ops = addon.operators
    obj = _import(tmp_path, _scene())
    bpy.ops.dresg.add_orbit_cameras(count=5)
    scene = bpy.context.scene
    objects = ops.views.scene_cameras(scene)
    capfd.readouterr()
    assert bpy.ops.dresg.select_views() == {"FINISHED"}  # background mode: on this thread, printed per camera
    lines = [line for line in capfd.readouterr().out.splitlines() if line.startswith("[select views]")]
    assert lines == [f"[select views] Rendering coverage: {k}/5 cameras ({objects[k - 1].name})" for k in range(1, 6)]

    cameras = ops.views.fitting_cameras(scene, obj, objects)
    splats = ops.splat_object.scene_from_object(obj)
    job = ops.views.SelectionJob(splats, cameras, scene.dresg.config(), [o.name for o in objects])
    job.start()
    fractions = []
    while not job.poll():
        fractions.append(job.fraction)
        time.sleep(0.001)
    assert job.reports == [(k, 5) for k in range(1, 6)] and job.fraction == 1.0
    assert all(b >= a for a, b in zip(fractions, fractions[1:])) and not math.isnan(job.fraction)
