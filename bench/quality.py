# SPDX-License-Identifier: GPL-3.0-or-later
"""Quality benchmark: does the stylized scene look like the painting, from views it was not fitted on?

    .venv/bin/python bench/quality.py [--quick] [--scenes bonsai,luigi,demo] [--styles starry_night,...]
        [--rows unstylized,colour-transfer,preview,standard] [--markdown out.md] [--json out.json]
        [--figures DIR] [--threads N]

Not a test: it prints a table. Scenes: the real bonsai (273k splats) and luigi (14.5k, y-up) from
``../shared/data/scenes``, the generated demo scene, and ``bonsai8``, the bonsai with each splat split into 8 inside
it (2.18M splats, a real capture's density; ``harness.densified``, asked for by name); styles: every painting in
``../shared/data/styles``, or by name, where ``demo`` (the demo's painting) and ``lines`` (a generated
pen-and-ink drawing) are made rather than read. Scenes and styles that are absent are skipped (the demo
scene and its painting always run).

Cameras. Each scene is stylized from 16 orbit cameras at 448x320 (the candidates of view selection) and
evaluated from 16 other orbit cameras on the same ring, half a step between them: novel views that were
never active, so a per-view proposal the scene could not absorb shows here.

Rows.
- ``unstylized``: the scene as it is.
- ``colour-transfer``: the paper's post stage alone: one covariance (affine) colour map from the base
  renders of the 16 cameras (covered pixels) to the style, applied to every splat's colour.
- ``preview`` and ``standard``: the stylizer's presets (the ``synth`` backend).

Columns, from ``dresg_addon.evaluation.views.evaluate_views`` (what ``dresg evaluate`` and ``dresg report`` give
too), means over the evaluation views, on the pixels the scene covers (alpha > 0.5):

- sliced-Wasserstein distance of 7x7 patches to the painting at three scales, the fit size (``SW patch``),
  half (``½``) and a quarter (``¼``): the novel views are rendered at twice the fit size and area-downsampled
  by 2, 4 and 8, and the painting is resampled the same way (its shorter side to the render's at each
  scale), so a 7x7 window sees brush texture at the fit size and strokes and flat areas at a quarter,
  the scale at which a person takes in a picture; lower is closer to the painting;
- the same distance on colours alone;
- SSIM and gradient structure to the unstylized render of the same camera (higher keeps more of the scene);
- ``texture kept``: the correlation of the luminance high-pass (finer than a Gaussian of sigma 2 px) of a novel
  view with that of the unstylized render, on the covered pixels at least 4 px inside the silhouette (1: the
  capture's own fine texture is all still there; about 0: replaced, by the painting's marks or by nothing;
  lower shows more of the painting's texture), and ``shapes``: SSIM of the two luminances blurred by a Gaussian
  of sigma 3 px (1: the same forms), and ``forms``: SSIM's structure term alone on those (1: the same forms at
  any brightness and contrast of the palette); all at the fit size (``metrics.texture_kept``,
  ``metrics.shape_similarity``, ``metrics.forms_similarity``); ``kept at 2x``: texture kept on the renders at
  twice the size, 8 px inside (the capture's detail finer than the fit size, which a closer look shows);
- mark contrast, ``marks fine``, ``mid`` and ``coarse`` (``metrics.mark_contrast``): the luminance band-pass
  (differences of Gaussians at sigma 0.6/1.2, 1.2/2.4 and 2.4/4.8 px) of the 2x render area-downsampled to the
  fit size, less the part the unstylized render's same band explains (least squares: the capture's texture taken
  out), 4 px inside the silhouette; its deviation over the painting's own, the painting resampled to the view's
  size x the run's Stroke Size (the standard preset's for the unstylized and colour-transfer rows). 1: marks as
  strong as the painting's; about 0: none (a colour transfer, a blur);
- ``elongation`` (``metrics.mark_length``): how long the marks run for their width, the fine band's correlation length
  along the local mark direction over that across it, over the painting's at the run's Stroke Size (1: strokes as
  elongated as the painting's; below: fragments, dabs and blobs);
- short- (neighbouring evaluation views) and long-range (opposite views) depth-warp RMSE (lower is more
  consistent; the unstylized row is the scene's own floor);
- how far the fit got, from the run's log (stylizer rows): the smallest share of a stage's target gap its
  fit closed (``closed``, target 50% at every stage);
- wall time of the stylization (what a user waits for); peak resident memory of its process. Each case runs in a
  fresh process.

Targets, as means over scene x style pairs: patch SW at least 30% below ``colour-transfer`` at the fit size
and half and 20% at a quarter, and below it on at least 15 of the 18 pairs at the coarsest; short-range RMSE at
most 1.2x ``colour-transfer``'s; texture kept <= 0.25 over the pairs (the painting's marks, not the capture's
texture); ``preview`` <= 60 s and ``standard`` <= 5 min on the bonsai, <= 8 GB. Per scene, as means over its
styles: forms >= 0.8 on every scene (the scene's forms still there); mark contrast fine >= 0.5 and mid >= 0.8 on
the bonsai and the demo, and no band above 1.3 (brush marks, not smudges or noise). SSIM to the base and shapes
are columns, not targets: SSIM rewards keeping the capture's texture, shapes a palette as bright as the capture.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import harness  # bench/, beside this script

from dresg_addon.util.machine import load_average

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DRESG_SHARED_DATA", REPO.parent / "shared" / "data"))
SCENES = {
    "bonsai": (SHARED / "scenes" / "bonsai-7k-mini.splat", (0.0, -1.0, 0.0)),
    "luigi": (SHARED / "scenes" / "luigi.ply", (0.0, 1.0, 0.0)),
    "demo": (None, (0.0, -1.0, 0.0)),
    "bonsai8": (SHARED / "scenes" / "bonsai-7k-mini.splat", (0.0, -1.0, 0.0)),  # each splat into 8: a capture's density
}
DENSIFIED = {"bonsai8": 8}  # scene -> children per splat (harness.densified)
ROWS = ("unstylized", "colour-transfer", "preview", "standard")
FULL = {"views": 16, "width": 448, "height": 320}
QUICK = {"views": 4, "width": 112, "height": 80}
QUICK_OVERRIDES = {"stages": 2, "proposal_width": 96, "proposal_height": 64}
QUICK_PLAN = {"updates_per_stage": 2, "fit_steps": 3, "post_steps": 3}
TARGET_PATCH_GAIN = (0.30, 0.30, 0.20)  # below the colour transfer at the fit size, half and a quarter (SCALES)
TARGET_COARSE_WINS = 15 / 18  # share of the pairs where the stylizer beats the colour transfer at a quarter
TARGET_TEXTURE_KEPT = 0.25  # the mean over the pairs
TARGET_MARKS = {"marks_fine": 0.5, "marks_mid": 0.8}  # per scene of MARKS_SCENES, the mean over its styles
TARGET_MARKS_MAX = 1.3  # no band above it there: marks, not noise
MARKS_SCENES = ("bonsai", "demo")
MARK_KEYS = ("marks_fine", "marks_mid", "marks_coarse")  # dresg_addon.evaluation.views.MARK_KEYS
TARGET_FORMS = 0.8  # per scene, the mean over its styles
TARGET_SHORT_RATIO = 1.2
TARGET_CLOSED = 0.5
TARGET_SECONDS = {"preview": 60.0, "standard": 300.0}
TARGET_DENSE_S, TARGET_DENSE_GB = 300.0, 4.0  # the default preset on the bonsai x 8 (a capture's 2M splats)
TARGET_ESTIMATE = 1.25  # the time left as estimated from stage 2 on, within this factor of the truth
SCALES = ("sw_patches", "sw_patches_half", "sw_patches_quarter")  # dresg_addon.evaluation.views.SCALES
COLUMNS = (
    ("sw_patches", "SW patch ↓", 4),
    ("sw_patches_half", "½ ↓", 4),
    ("sw_patches_quarter", "¼ ↓", 4),
    ("sw_colors", "SW colour ↓", 4),
    ("ssim", "SSIM ↑", 3),
    ("structure", "GS ↑", 3),
    ("texture_kept", "texture kept ↓", 3),
    ("texture_kept_2x", "kept at 2x ↓", 3),
    ("shapes", "shapes ↑", 3),
    ("forms", "forms ↑", 3),
    ("marks_fine", "marks fine", 2),
    ("marks_mid", "mid", 2),
    ("marks_coarse", "coarse", 2),
    ("mark_elongation", "elongation", 2),
    ("short_rmse", "short RMSE ↓", 4),
    ("long_rmse", "long RMSE ↓", 4),
    ("min_closed", "closed ↑", 2),
)


# --- worker side (one subprocess per case) ---------------------------------------------------------------


def _generated():
    from dresg_addon.scene.demo import demo_style_image, line_drawing_image

    return {"demo": demo_style_image, "lines": line_drawing_image}


GENERATED = {"demo": lambda: _generated()["demo"](), "lines": lambda: _generated()["lines"]()}  # made, not read


def style_path(name: str) -> Path | None:
    path = SHARED / "styles" / f"{name}.jpg"
    return path if path.is_file() else None


def load_case(spec: dict):
    """(scene, training cameras, evaluation cameras, style [H, W, 3]) of a case."""
    from dresg_addon.scene.demo import demo_scene
    from dresg_addon.scene.io import read_scene
    from dresg_addon.scene.orbit import orbit_cameras
    from dresg_addon.util.imageio import read_rgb

    path, up = SCENES[spec["scene"]]
    scene = demo_scene() if path is None else read_scene(path)
    if spec["scene"] in DENSIFIED:
        scene = harness.densified(scene, DENSIFIED[spec["scene"]])
    if spec.get("subsample", 1) > 1:
        scene = scene.subset(slice(None, None, spec["subsample"]))
    size = {"width": spec["width"], "height": spec["height"], "up": up}
    train = orbit_cameras(scene, spec["views"], **size)
    novel = orbit_cameras(scene, spec["views"], azimuth_offset_deg=180.0 / spec["views"], **size)
    style = GENERATED[spec["style"]]() if spec["style"] in GENERATED else read_rgb(style_path(spec["style"]))
    return scene, train, novel, style


def colour_transfer_scene(scene, cameras, style):
    """The post stage alone: one covariance colour map, fitted on the covered pixels of the base renders."""
    import torch

    from dresg_addon.method.color_transfer import transfer_scene_colors
    from dresg_addon.raster import render_scene

    renders = [render_scene(scene, camera) for camera in cameras]
    stack = torch.stack([r.rgb.permute(2, 0, 1) for r in renders])
    style_chw = torch.from_numpy(style).permute(2, 0, 1).contiguous()
    return transfer_scene_colors(scene, stack, torch.stack([r.alpha for r in renders]), style_chw)


def fit_summary(log: list[dict]) -> dict:
    """The smallest share of a stage's target gap its fit closed, and each stage's."""
    closed = [e["gap_closed"] for e in log if e.get("target_gap")]
    return {"min_closed": min(closed) if closed else None, "closed_per_stage": closed}


def run_case(spec: dict) -> dict:
    """Stylize one (scene, style) with one row's method, then evaluate it on the novel views."""
    import numpy as np

    from dresg_addon.evaluation.views import base_views, evaluate_views
    from dresg_addon.method.config import preset
    from dresg_addon.method.loop import stylize
    from dresg_addon.util.imageio import write_image

    scene, train, novel, style = load_case(spec)
    started = time.perf_counter()
    row = spec["row"]
    log, estimates = [], []
    stroke_size = preset("standard").stroke_size  # mark contrast's painting scale where no stylizer run sets one
    if row == "unstylized":
        out = scene
    elif row == "colour-transfer":
        out = colour_transfer_scene(scene, train, style)
    else:
        name, changes, plan_changes = row_settings(row)
        config = preset(name, **spec.get("overrides", {}), **changes)
        plan = config.plan().with_(**spec.get("plan", {}), **plan_changes)

        def progress(p):  # (seconds since the start, the estimate of the time left) as each stage from 2 on begins
            if p.phase == "proposal" and p.stage >= 2 and p.step == 0 and math.isfinite(p.eta_seconds):
                estimates.append((time.perf_counter() - started, p.eta_seconds))

        result = stylize(scene, train, style, config, plan=plan, progress=progress)
        out, log, stroke_size = result.scene, result.log, config.stroke_size
    seconds = time.perf_counter() - started
    peak = harness.peak_rss_bytes()
    base = base_views(scene, novel)
    measured = evaluate_views(out, base, style, stroke_size=stroke_size)
    if spec.get("figures"):
        folder = Path(spec["figures"])
        for i, (before, after) in enumerate(zip(base.renders.rgb, measured.renders_2x)):
            if i in spec.get("figure_views", (0,)):
                name = f"{spec['scene']}_{spec['style']}_{row}_v{i:02d}.png"
                write_image(folder / name, np.ascontiguousarray(after.permute(1, 2, 0)))
                if row == "unstylized":
                    write_image(
                        folder / f"{spec['scene']}_v{i:02d}_1x.png", np.ascontiguousarray(before.permute(1, 2, 0))
                    )
    stages = [e for e in log if e.get("stage") != "post"]
    ratios = [eta / (seconds - at) for at, eta in estimates if seconds - at > 0]
    return {
        **measured.mean,
        **fit_summary(log),
        "estimate_ratios": ratios,  # the estimate of the time left over the time it took, at each stage from 2 on
        "seconds": seconds,
        "peak_rss": peak,
        "gaussians": len(scene),
        "stages": len(stages),
        "views": stages[0]["views"] if stages else 0,
    }


def row_settings(row: str) -> tuple[str, dict, dict]:
    """A stylizer row's preset and its changed settings and plan fields:
    ``standard@stroke_size=2,best_views=2`` -> ("standard", {"stroke_size": 2.0}, {"best_views": 2.0})."""
    from dataclasses import fields

    from dresg_addon.method.config import PRESETS, Plan

    name, _, rest = row.partition("@")
    changes, plan_changes = {}, {}
    kinds = {f.name: (type(getattr(PRESETS["paper"], f.name)), changes) for f in fields(PRESETS["paper"])}
    kinds.update({f.name: (type(getattr(Plan(), f.name)), plan_changes) for f in fields(Plan)})
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if key not in kinds:
            raise SystemExit(
                f"quality bench: {key!r} in row {row!r} is neither a StylizeConfig setting nor a Plan field"
            )
        kind, into = kinds[key]
        if kind not in (bool, int, float, str):
            raise SystemExit(f"quality bench: {key!r} in row {row!r} cannot be set from a row")
        parse = (lambda v: v.lower() in ("1", "true", "on")) if kind is bool else kind
        into[key] = parse(value)
    return name, changes, plan_changes


def run_baseline(spec: dict) -> dict:
    import torch

    import dresg_addon.method.loop  # noqa: F401

    return {"torch": torch.__version__, "threads": torch.get_num_threads(), "peak_rss": harness.peak_rss_bytes()}


WORKERS = {"case": run_case, "baseline": run_baseline}


# --- driver side -----------------------------------------------------------------------------------------


def fmt(value, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def mean(values) -> float | None:
    present = [v for v in values if v is not None]
    return sum(present) / len(present) if present else None


def table(rows: list[tuple[str, dict]]) -> list[str]:
    head = "| row | " + " | ".join(label for _, label, _ in COLUMNS) + " | time | peak memory |"
    out = [head, "|---|" + "---:|" * (len(COLUMNS) + 2)]
    for name, r in rows:
        if "error" in r:
            out.append(f"| {name} | {r['error']} |" + " |" * (len(COLUMNS) + 1))
            continue
        cells = [fmt(r.get(key), digits) for key, _, digits in COLUMNS]
        out.append(f"| {name} | " + " | ".join(cells) + f" | {r['seconds']:.1f} s | {r['peak_rss'] / 1e9:.2f} GB |")
    return out


def verdicts(results: dict, rows: list[str], quick: bool) -> list[str]:
    """The issue's targets, on the means over every (scene, style) pair that ran all rows."""
    means = {row: {} for row in rows}
    for row in rows:
        cases = [c[row] for c in results.values() if row in c and "error" not in c[row]]
        for key, _, _ in COLUMNS:
            means[row][key] = mean(c.get(key) for c in cases)
        means[row]["seconds"] = mean(c["seconds"] for c in cases)
    lines = [
        "| row | " + " | ".join(label for _, label, _ in COLUMNS) + " | time |",
        "|---|" + "---:|" * (len(COLUMNS) + 1),
    ]
    for row in rows:
        cells = [fmt(means[row][key], digits) for key, _, digits in COLUMNS]
        lines.append(f"| {row} | " + " | ".join(cells) + f" | {fmt(means[row]['seconds'], 1)} s |")
    ct = means.get("colour-transfer", {})

    def met(ok: bool) -> str:
        return "met" if ok else "NOT met"

    for row in ("preview", "standard"):
        if row not in means or not ct or means[row]["sw_patches"] is None or ct.get("sw_patches") is None:
            continue
        m = means[row]
        gains = [1.0 - m[key] / ct[key] for key in SCALES]
        pairs = [c for c in results.values() if "error" not in c.get(row, {"error": 1}) and "colour-transfer" in c]
        wins = sum(c[row]["sw_patches_quarter"] < c["colour-transfer"]["sw_patches_quarter"] for c in pairs)
        needed = math.ceil(TARGET_COARSE_WINS * len(pairs))
        short_ratio = (m["short_rmse"] or 0.0) / max(ct.get("short_rmse") or 1e-12, 1e-12)
        closed = [c[row]["min_closed"] for c in pairs if c[row].get("min_closed") is not None]
        gains_met = all(g >= t for g, t in zip(gains, TARGET_PATCH_GAIN))
        lines.append(
            f"- {row}: patch SW below the colour transfer by {', '.join(f'{100 * g:.0f}%' for g in gains)} at the fit "
            f"size, half and a quarter (target >= {', '.join(f'{100 * t:.0f}%' for t in TARGET_PATCH_GAIN)}: "
            f"{met(gains_met)}); below it at a quarter on {wins} of {len(pairs)} pairs "
            f"(target >= {needed}: {met(wins >= needed)}); SSIM {m['ssim']:.3f} (no target: it rewards keeping the "
            f"capture's texture); short-range RMSE {short_ratio:.2f}x the colour transfer's (target <= "
            f"{TARGET_SHORT_RATIO}x: {met(short_ratio <= TARGET_SHORT_RATIO)})"
        )
        scenes = {}
        for (scene, _), c in results.items():
            if row in c and "error" not in c[row]:
                scenes.setdefault(scene, []).append(c[row])
        per_scene = {
            key: {s: v for s, cs in scenes.items() if (v := mean(c.get(key) for c in cs)) is not None}
            for key in ("texture_kept", "forms", *MARK_KEYS)
        }
        texture, forms = per_scene["texture_kept"], per_scene["forms"]
        if texture:
            text = (
                f"  - texture kept {m['texture_kept']:.3f} over the pairs, per scene "
                f"{', '.join(f'{s} {v:.3f}' for s, v in texture.items())} (target <= {TARGET_TEXTURE_KEPT} over the "
                f"pairs: {met(m['texture_kept'] <= TARGET_TEXTURE_KEPT)})"
            )
            if forms:  # runs from before the column have none
                text += (
                    f"; forms {', '.join(f'{s} {v:.3f}' for s, v in forms.items())} (target >= {TARGET_FORMS} on "
                    f"every scene: {met(min(forms.values()) >= TARGET_FORMS)})"
                )
            lines.append(text)
        marked = [s for s in scenes if all(s in per_scene[key] for key in MARK_KEYS)]
        if marked:
            values = ", ".join(f"{s} " + "/".join(f"{per_scene[key][s]:.2f}" for key in MARK_KEYS) for s in marked)
            judged = [s for s in marked if s in MARKS_SCENES]
            ok = judged and all(
                all(per_scene[key][s] >= low for key, low in TARGET_MARKS.items())
                and max(per_scene[key][s] for key in MARK_KEYS) <= TARGET_MARKS_MAX
                for s in judged
            )
            verdict = met(bool(ok)) if judged else f"none of {' and '.join(MARKS_SCENES)} ran"
            lines.append(
                f"  - mark contrast fine/mid/coarse {values} (target fine >= {TARGET_MARKS['marks_fine']} and mid >= "
                f"{TARGET_MARKS['marks_mid']}, no band above {TARGET_MARKS_MAX}, on the {' and the '.join(MARKS_SCENES)}"
                f": {verdict})"
            )
        if m.get("texture_kept_2x") is not None:  # runs from before the column have none
            lines.append(
                f"  - texture kept at twice the size {m['texture_kept_2x']:.3f} (no target: the capture's detail "
                "finer than the fit size, which a closer look shows)"
            )
        if closed:
            lines.append(
                f"  - the fit: every stage closed at least {100 * min(closed):.0f}% of its target gap (target "
                f"{100 * TARGET_CLOSED:.0f}% at every stage: {met(min(closed) >= TARGET_CLOSED)})"
            )
    if not quick:
        for row, limit in TARGET_SECONDS.items():
            bonsai = [
                c[row] for (scene, _), c in results.items() if scene == "bonsai" and row in c and "error" not in c[row]
            ]
            if bonsai:
                worst = max(c["seconds"] for c in bonsai)
                memory = max(c["peak_rss"] for c in bonsai) / 1e9
                lines.append(
                    f"- {row} on the bonsai: up to {worst:.0f} s (target <= {limit:.0f} s: {met(worst <= limit)}), "
                    f"peak memory up to {memory:.2f} GB (target <= 8 GB: {met(memory <= 8)})"
                )
        dense = [
            c[row] for (scene, _), c in results.items() if scene == "bonsai8" for row in c if "error" not in c[row]
        ]
        dense = [c for c in dense if "estimate_ratios" in c and c["estimate_ratios"]]
        if dense:
            worst = max(c["seconds"] for c in dense)
            memory = max(c["peak_rss"] for c in dense) / 1e9
            ratios = [r for c in dense for r in c["estimate_ratios"]]
            within = max(max(ratios), 1 / min(ratios)) <= TARGET_ESTIMATE
            lines.append(
                f"- the bonsai x 8 (2.18M splats): up to {worst:.0f} s (target <= {TARGET_DENSE_S:.0f} s: "
                f"{met(worst <= TARGET_DENSE_S)}), peak memory up to {memory:.2f} GB (target <= {TARGET_DENSE_GB:g} GB: "
                f"{met(memory <= TARGET_DENSE_GB)}); the time left as estimated from stage 2 on, over the truth: "
                f"{min(ratios):.2f}-{max(ratios):.2f} (target within {TARGET_ESTIMATE}x: {met(within)})"
            )
    return lines


def split_rows(text: str) -> list[str]:
    """The rows of ``--rows``: ';'-separated when there is a ';', else ','-separated, where a piece that is only a
    setting (``key=value``, no row name) belongs to the row before it: ``standard@stroke_size=2,scene_light=0``."""
    if ";" in text:
        return [r for r in text.split(";") if r]
    rows: list[str] = []
    for piece in filter(None, text.split(",")):
        if rows and "@" in rows[-1] and "=" in piece and "@" not in piece:
            rows[-1] += "," + piece
        else:
            rows.append(piece)
    return rows


def report_from_json(paths: list[str], rows: list[str]) -> int:
    """Print the per-pair tables and the targets again from ``--json`` files, without running anything.

    Several files (runs split across processes) merge pair by pair; a later file's row replaces an earlier one's.
    """
    results: dict[tuple[str, ...], dict] = {}
    for path in paths:
        for key, cases in json.loads(Path(path).read_text(encoding="utf-8")).items():
            results.setdefault(tuple(key.split("/", 1)), {}).update(cases)
    out = []
    for (scene, style), cases in results.items():
        out += [f"### {scene} x {style}", "", *table([(row, cases[row]) for row in rows if row in cases]), ""]
    out += [f"### Means over {len(results)} scene x style pairs", "", *verdicts(results, rows, False), ""]
    print("\n".join(out))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: demo scene, 4 cameras at 112x80, tiny schedules"
    )
    parser.add_argument(
        "--scenes", default="bonsai,luigi,demo", help="comma-separated: bonsai, luigi, demo, bonsai8 (the bonsai x 8)"
    )
    parser.add_argument("--styles", help="comma-separated style names (default: every shared painting, or the demo's)")
    parser.add_argument(
        "--rows",
        default=",".join(ROWS),
        help="comma-separated rows (default: all); a stylizer row may change settings, e.g. "
        "'standard,standard@stroke_size=2,scene_light=0' (a bare key=value belongs to the row before it; "
        "or separate the rows by ';')",
    )
    parser.add_argument("--markdown", metavar="FILE", help="also write the report to FILE (markdown)")
    parser.add_argument(
        "--json", metavar="FILE", help="also write every measurement to FILE (rewritten after each pair)"
    )
    parser.add_argument("--figures", metavar="DIR", help="write novel-view renders at 2x of every case to DIR")
    parser.add_argument("--figure-views", default="0", help="comma-separated novel-view indices to write (default 0)")
    parser.add_argument("--threads", type=int, help="torch threads in every case (default: torch's own choice)")
    parser.add_argument(
        "--from-json",
        metavar="FILE",
        nargs="+",
        help="print the tables of earlier runs' --json files again (several: merged pair by pair)",
    )
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return harness.run_worker(args.worker, WORKERS)
    if args.from_json:
        return report_from_json(args.from_json, split_rows(args.rows))

    size = QUICK if args.quick else FULL
    scenes = [s for s in args.scenes.split(",") if s]
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        parser.error(f"unknown scene(s): {', '.join(unknown)} (choose from {', '.join(SCENES)})")
    scenes = [s for s in scenes if SCENES[s][0] is None or SCENES[s][0].is_file()]
    if args.styles:
        styles = [s for s in args.styles.split(",") if s]
    else:
        styles = sorted(p.stem for p in (SHARED / "styles").glob("*.jpg")) or ["demo"]
    styles = [s for s in styles if s in GENERATED or style_path(s) is not None] or ["demo"]
    if args.quick:
        scenes, styles = scenes[:1] if "demo" not in scenes else ["demo"], styles[:2]
    rows = split_rows(args.rows)
    unknown_rows = [r for r in rows if r.partition("@")[0] not in ROWS]
    if unknown_rows:
        parser.error(f"unknown row(s): {', '.join(unknown_rows)} (choose from {', '.join(ROWS)})")
    common = {**size, "threads": args.threads, "figures": args.figures}
    common["figure_views"] = [int(v) for v in args.figure_views.split(",") if v]
    if args.quick:
        common["overrides"], common["plan"] = QUICK_OVERRIDES, QUICK_PLAN
    if args.figures:
        Path(args.figures).mkdir(parents=True, exist_ok=True)

    started = time.perf_counter()
    baseline = harness.call_worker(__file__, {"kind": "baseline", **common})
    title = "## Quality benchmark" + (" (quick smoke run: says nothing about the targets)" if args.quick else "")
    out = [
        title,
        "",
        harness.machine_line(baseline),
        f"- load average (1, 5, 15 min) at start: {load_average()}",
        f"- cameras: {size['views']} orbit views at {size['width']}x{size['height']} to stylize from, "
        f"{size['views']} novel views between them to evaluate on; metrics on covered pixels",
        "",
    ]
    print("\n".join(out), flush=True)
    results: dict = {}
    for scene in scenes:
        for style in styles:
            case_rows = []
            for row in rows:
                print(f"  {scene} x {style}: {row} ...", file=sys.stderr, flush=True)
                spec = {"kind": "case", "scene": scene, "style": style, "row": row, **common}
                result = harness.call_worker(__file__, spec)
                results.setdefault((scene, style), {})[row] = result
                case_rows.append((row, result))
            lines = [f"### {scene} x {style}", "", *table(case_rows), ""]
            print("\n".join(lines), flush=True)
            out += lines
            if args.json:  # after every pair, so a run stopped early keeps what it measured (see --from-json)
                write_json(args.json, results)
    lines = [f"### Means over {len(results)} scene x style pairs", "", *verdicts(results, rows, args.quick), ""]
    lines.append(
        f"Benchmark wall time: {(time.perf_counter() - started) / 60:.1f} min; load average at the end: {load_average()}."
    )
    print("\n".join(lines), flush=True)
    out += lines
    if args.markdown:
        Path(args.markdown).write_text("\n".join(out) + "\n", encoding="utf-8")
    if args.json:
        write_json(args.json, results)
    return 0


def write_json(path: str, results: dict) -> None:
    from dresg_addon.util.fileutil import atomic_write_bytes

    flat = {f"{scene}/{style}": cases for (scene, style), cases in results.items()}
    atomic_write_bytes(path, json.dumps(flat, indent=1).encode("utf-8"))


if __name__ == "__main__":
    sys.exit(main())
