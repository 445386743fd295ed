# SPDX-License-Identifier: GPL-3.0-or-later
"""What the benchmark scripts share: one fresh interpreter per case, and the machine header."""

from __future__ import annotations

import json
import platform
import resource
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dresg_addon.machine import cpu_model, usable_cores  # noqa: E402  (needs the repository on the path)


def peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB


def call_worker(script: str, spec: dict) -> dict:
    """Run ``script --worker SPEC`` in a fresh interpreter; ``{'error': ...}`` when it fails (e.g. killed for memory)."""
    done = subprocess.run(
        [sys.executable, str(Path(script).resolve()), "--worker", json.dumps(spec)], capture_output=True, text=True
    )
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        return {"error": f"failed: {tail}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_worker(payload: str, workers: dict) -> int:
    """The worker side of :func:`call_worker`: run ``workers[spec['kind']]`` and print its JSON result."""
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
