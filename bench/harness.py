# SPDX-License-Identifier: GPL-3.0-or-later
"""What the benchmark scripts share: one fresh interpreter per case, its thread policy, and the machine header."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from dresg_addon.util.machine import cpu_model, peak_rss_mb, usable_cores
from dresg_addon.util.threads import ThreadAdapter, apply_thread_policy

REPO = Path(__file__).resolve().parents[1]


def load_addon():
    """This checkout's Blender extension, registered (bpy module), through the headless script: Blender's entry
    point, run by path as ``blender -P`` runs it."""
    import runpy

    return runpy.run_path(str(REPO / "scripts" / "stylize_headless.py"))["load_addon"]()


def peak_rss_bytes() -> int:
    return int(peak_rss_mb() * 2**20)


THREAD_SETTINGS = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
THREADS = ThreadAdapter()  # a worker's torch threads: the benches adapt them between timed runs and steps
LOADS = {  # what else runs on the machine while a loaded case is measured
    "python": "while True: pass",  # one core taken by a process that never waits
    # another torch job doing small ops with torch's default threads, which spin between ops
    "torch": "import torch\na = torch.randn(64, 64)\nwhile True:\n    b = a @ a + a.sin()",
}


def default_environment() -> dict:
    """This environment without OpenMP wait settings: a load process runs as torch does by default."""
    return {key: value for key, value in os.environ.items() if key not in THREAD_SETTINGS}


@contextmanager
def background_load(kind: str, settle_s: float = 2.0):
    """Run one :data:`LOADS` process for the duration of the block (started and stopped here)."""
    process = subprocess.Popen([sys.executable, "-c", LOADS[kind]], env=default_environment())
    try:
        time.sleep(settle_s)  # let it start (torch takes a second to import)
        yield
    finally:
        process.kill()
        process.wait()


def call_worker(script: str, spec: dict) -> dict:
    """Run ``script --worker SPEC`` in a fresh interpreter; ``{'error': ...}`` when it fails (e.g. killed for memory)."""
    done = subprocess.run(
        [sys.executable, str(Path(script).resolve()), "--worker", json.dumps(spec)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        return {"error": f"failed: {tail}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_worker(payload: str, workers: dict) -> int:
    """The worker side of :func:`call_worker`: run ``workers[spec['kind']]`` and print its JSON result.

    The worker owns its process: the thread policy is set here, before a case loads torch, as the CLI's
    ``main`` sets it (what a user set in the environment wins).
    """
    apply_thread_policy()
    spec = json.loads(payload)
    if spec.get("threads"):
        import torch

        torch.set_num_threads(spec["threads"])
    print(json.dumps(workers[spec["kind"]](spec)))
    return 0


def machine_line(baseline: dict, with_os: bool = False) -> str:
    """'- machine: CPU, cores, (OS,) Python, torch version and threads' (torch's from a worker's ``baseline``)."""
    system = f" {platform.system()} {platform.release()}," if with_os else ""
    return (
        f"- machine: {cpu_model()}, {usable_cores()} cores usable,{system} Python {platform.python_version()}, "
        f"torch {baseline.get('torch', '?')}, torch threads: {baseline.get('threads', '?')}"
    )


def densified(scene, factor: int, seed: int = 0):
    """A dense capture's stand-in: each splat replaced by ``factor`` children inside it, scales x s with
    s = factor^(-1/3), centres drawn from the parent's Gaussian shrunk by sqrt(1 - s^2) (the mixture keeps the parent's
    covariance), opacity alpha / (factor s^2) (the children's footprints carry the parent's). The bonsai x 8 holds
    2.18M splats, about what a real capture holds, and renders close to the source."""
    from dataclasses import replace

    import numpy as np

    rng = np.random.default_rng(seed)
    shrink = factor ** (-1.0 / 3.0)
    parent = np.repeat(np.arange(len(scene)), factor)
    q = scene.quats.astype(np.float64)
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True).clip(1e-30)).T
    rotation = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)  # [N, 3, 3]
    local = rng.standard_normal((len(parent), 3)) * np.exp(scene.log_scales[parent].astype(np.float64))
    offsets = np.einsum("nij,nj->ni", rotation[parent], local) * np.sqrt(1.0 - shrink**2)
    alpha = 1.0 / (1.0 + np.exp(-scene.opacity_logits.astype(np.float64)))
    child = np.clip(alpha / (factor * shrink**2), 1e-4, 0.999)
    return replace(
        scene.subset(parent),
        means=(scene.means[parent] + offsets).astype(np.float32),
        log_scales=(scene.log_scales[parent] + np.log(shrink)).astype(np.float32),
        opacity_logits=np.log(child / (1.0 - child))[parent].astype(np.float32),
    )
