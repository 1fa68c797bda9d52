"""fuzz.md: the fuzzer's figures (``fuzz.json``, ``platoon_opt.study.fuzz``) as markdown."""

from __future__ import annotations

import statistics
from collections import Counter
from typing import Any

from platoon_opt.study.markdown import duration_text, table

VERDICTS = ("run", "error", "strict stop", "finding")
# Findings shown in fuzz.md (fuzz.json keeps up to fuzz.KEPT per chunk).
SHOWN = 10


def markdown(result: dict[str, Any]) -> str:
    """fuzz.md: what ran; per family the cases of each verdict and the time per case; the
    findings with their reproduction."""
    families: dict[str, Counter[str]] = {}
    seconds: dict[str, list[float]] = {}
    for chunk in result["chunks"]:
        families.setdefault(chunk["family"], Counter()).update(chunk["verdicts"])
        seconds.setdefault(chunk["family"], []).extend(chunk["seconds"])
    every = [s for values in seconds.values() for s in values]
    counts: Counter[str] = sum(families.values(), Counter())
    lines = [
        "# Fuzzing the command line",
        "",
        f"Command: `{result['command']}`. {result['date']}, {result['machine'].get('cpu', '')}; "
        f"code `{result['code']}`, seed {result['seed']}.",
        "",
        f"**{len(every):,} cases, {counts['finding']:,} findings**; {counts['run']:,} sane runs (exit 0), "
        f"{counts['error']:,} one-line errors (exit 2), {counts['strict stop']:,} `--strict` stops "
        f"(exit 3). Time per case: median {1e3 * statistics.median(every or [0]):.0f} ms, "
        f"{duration_text(sum(every))} in all ({result['reused']:,} cases reused from an earlier call).",
        "",
        "A case passes with exit 0 and a sane run (finite metrics, the steps asked for, its files) or",
        "exit 2 with one stderr line naming the file, key and value (a scenario file) or the flag and",
        "value (an argument list); anything else is a finding. docs/cli.md describes the families.",
        "",
    ]
    rows = [
        [f"`{name}`", f"{sum(verdicts.values()):,}", *(f"{verdicts[v]:,}" for v in VERDICTS)]
        + [f"{1e3 * statistics.median(seconds[name]):.0f}"]
        for name, verdicts in families.items()
    ]
    lines.append(table(["family", "cases", *VERDICTS, "median ms per case"], rows))
    findings = sorted((f for chunk in result["chunks"] for f in chunk["findings"]), key=lambda f: f["index"])
    if not findings:
        lines.append("No findings.\n")
        return "\n".join(lines)
    lines.append(f"## Findings (first {min(SHOWN, len(findings))} of {counts['finding']:,})\n")
    lines.append("`platoon-opt fuzz --show INDEX` prints a case's argv and file.\n")
    for finding in findings[:SHOWN]:
        lines.append(f"### case {finding['index']}: {finding['family']} ({finding['kind']})\n")
        lines.append(f"{finding['note']}; exit {finding['status']}: {'; '.join(finding['problems'])}\n")
        lines.append("```\nplatoon-opt " + " ".join(finding["argv"]) + "\n```\n")
    return "\n".join(lines)
