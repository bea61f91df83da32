"""Run every benchmark and write BENCHMARKS.md (median of repeats, machine, peers).

Usage: python benchmarks/run_all.py [--out BENCHMARKS.md] [--repeats N]
                                   [--train-report DIR/train.json ...]

The existing output file's notes are kept, and without --train-report its training section.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import Row
from training_report import HEADING as TRAINING_HEADING
from training_report import render as render_training
from vistac.allocator import keep_freed_memory

MODULES = (
    "bench_sim",
    "bench_cli",
    "bench_shape_fit",
    "bench_shape_views",
    "bench_filter",
    "bench_actions",
    "bench_touch_pf",
    "bench_touch_gpis",
)


def machine() -> str:
    """The CPU in words: its name, family and model (CPUs of one name differ by generation)
    and whether it has AVX-512 (torch's kernels use it), the core count, Python and OS."""
    fields: dict[str, str] = {}
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            key, _, value = line.partition(":")
            fields.setdefault(key.strip(), value.strip())
    cpu = fields.get("model name", "unknown CPU")
    if "cpu family" in fields:
        avx512 = "avx512f" in fields.get("flags", "").split()
        cpu += (f" (family {fields['cpu family']}, model {fields.get('model', '?')}, "
                f"{'with' if avx512 else 'no'} AVX-512)")  # fmt: skip
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {platform.system()}"


def render(rows: list[Row], repeats: int) -> str:
    lines = [
        "# Benchmarks",
        "",
        f"Machine: {machine()}. Date: {datetime.date.today().isoformat()}. "
        f"Each figure is the median of {repeats} repeats after a warm-up unless its note gives "
        "another count; peers are measured in the same run unless the peer says otherwise. "
        "Regenerate with `make bench`.",
        "",
        "| benchmark | vistac | target | met | peer (same run) | note |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        peer = f"{row.peer}: {row.peer_value:.4g} {row.unit}" if row.peer_value is not None else "-"
        lines.append(
            f"| {row.name} | {row.value:.4g} {row.unit} | {row.target} | "
            f"{'yes' if row.passed else '**no**'} | {peer} | {row.note} |"
        )
    return "\n".join(lines) + "\n"


NOTES_HEADING = "## Notes"


def kept_sections(out: Path) -> tuple[str, str]:
    """The notes and the training section of an earlier ``out`` (each from its heading on),
    '' for a section it lacks.

    A rerun keeps the notes (written by hand: the machines, the changes measured back to
    back) and, without ``--train-report``, the training rows it cannot measure itself."""
    text = out.read_text(encoding="utf-8") if out.is_file() else ""
    training_at = text.find(f"\n{TRAINING_HEADING}")
    training = text[training_at:] if training_at >= 0 else ""
    notes_at = text.find(f"\n{NOTES_HEADING}\n")
    end = training_at if training_at > notes_at else len(text)
    notes = text[notes_at:end] if notes_at >= 0 else ""
    return notes, training


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", type=Path, default=Path("BENCHMARKS.md"))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument(
        "--train-report", type=Path, action="append", default=[],
        help="a train.json of `vistac train` to report (training time, trajectories)",
    )  # fmt: skip
    args = parser.parse_args()
    missing = [str(path) for path in args.train_report if not path.is_file()]
    if missing:
        print(f"error: no such train.json: {', '.join(missing)} (write one with `vistac train "
              "SKILL --out DIR`)", file=sys.stderr)  # fmt: skip
        return 2
    keep_freed_memory()  # as the vistac command does
    rows: list[Row] = []
    for name in MODULES:
        print(f"running {name} ...", flush=True)
        rows += importlib.import_module(name).run(args.repeats)
    notes, training = kept_sections(args.out)
    text = render(rows, args.repeats) + notes + (render_training(args.train_report) or training)
    args.out.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
