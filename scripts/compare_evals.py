"""``ns-eval`` JSONs of single runs side by side: PSNR / SSIM on each run's own held-out images, grouped by dataset.

For questions such as "does a capture posed another way train a worse NeRF, or is the difference nerfacto's
run-to-run spread?": each entry is ``group/label=path`` (``group`` names the dataset, ``label`` the training), and
every label of a group is compared with the group's first. The JSONs come from
``ns-eval --load-config <run>/config.yml --output-path <path>`` (the run's own eval split, posed by its own dataset,
so no registration or ground truth is involved).

Example::

    python scripts/compare_evals.py --entries oc14-a/seed42=a.json oc14-a/seed43=b.json \\
        --output reports/run_spread_oc14.md --command "..."
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from nerfuser_ns.files import write_text_atomic


@dataclass
class CompareEvals:
    """Tabulate ns-eval results of single runs, grouped by dataset."""

    entries: list[str]
    """``group/label=path`` per ns-eval JSON."""
    output: Path
    """Markdown report."""
    command: str = ""
    """The commands that made the JSONs (heads the report)."""
    note: str = ""
    """A paragraph under the command."""
    metrics: list[str] = field(default_factory=lambda: ["psnr", "ssim"])
    """Keys of ns-eval's ``results`` to show."""

    def main(self) -> None:
        groups: dict[str, list[tuple[str, dict]]] = {}
        for entry in self.entries:
            name, sep, path = entry.partition("=")
            group, slash, label = name.partition("/")
            if not sep or not slash or not group or not label:
                raise SystemExit(f"compare_evals: entry {entry!r} is not group/label=path")
            file = Path(path)
            if not file.is_file():
                raise SystemExit(f"compare_evals: {file} does not exist; run ns-eval for {name} first")
            results = json.loads(file.read_text()).get("results")
            if not isinstance(results, dict) or any(m not in results for m in self.metrics):
                raise SystemExit(f"compare_evals: {file} has no ns-eval results with {', '.join(self.metrics)}")
            groups.setdefault(group, []).append((label, results))
        head = ["dataset", "training", *self.metrics, *(f"{m} - first" for m in self.metrics)]
        lines = ["# ns-eval of single runs on their own held-out images", ""]
        if self.command:
            lines += [f"Commands: {self.command}", ""]
        if self.note:
            lines += [self.note, ""]
        lines += ["| " + " | ".join(head) + " |", "| " + " | ".join("---" for _ in head) + " |"]
        for group, rows in groups.items():
            first = rows[0][1]
            for label, results in rows:
                values = [f"{results[m]:.4f}" for m in self.metrics]
                deltas = [f"{results[m] - first[m]:+.4f}" for m in self.metrics]
                lines.append("| " + " | ".join([group, label, *values, *deltas]) + " |")
        write_text_atomic(self.output, "\n".join(lines) + "\n")
        print(f"wrote {self.output}")


if __name__ == "__main__":
    tyro.cli(CompareEvals).main()
