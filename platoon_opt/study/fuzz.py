"""Mutated scenario files and argument lists through the command line's entry point, each exit
judged: a sane run or one clear line, never a traceback (``platoon-opt fuzz``, docs/cli.md).

Case ``i`` of seed ``s`` belongs to family ``FAMILIES[i % len(FAMILIES)]`` and is drawn from
``random.Random("platoon-opt-fuzz:s:i")``: a shipped scenario file mutated (``fuzz_files``) and
run through ``simulate`` or ``compare`` for a few steps, or an argument list (``fuzz_argv``). It
runs in this process through ``cli.main`` in a fresh folder and is judged by ``fuzz_oracle``, the
oracle the hypothesis test (tests/study/test_fuzz.py) uses too.

Resumable as the soak (``study.soak``): a family's cases run in chunks of ``CHUNK``; each finished
chunk's record is stored at once in a ``ResultCache`` under ``<out>/fuzz-chunks/<family>/<chunk>``
with a fingerprint of the seed, the chunk's cases and the code (every source file of the package
and the shipped scenarios: the fuzzer judges the whole command line), so that the same command
after an interruption reruns only the chunks under way. ``fuzz.json`` and ``fuzz.md``
(``fuzz_report``) are written at the end.
"""

from __future__ import annotations

import argparse
import base64
import datetime
import functools
import hashlib
import math
import random
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any, TextIO

from platoon_opt.scenarios import tomllib
from platoon_opt.study.arguments import CASES, SEED
from platoon_opt.study.cache import ResultCache, fingerprint
from platoon_opt.study.executor import Progress
from platoon_opt.study.exits import stopped
from platoon_opt.study.fuzz_argv import ARGV_FAMILIES, arguments
from platoon_opt.study.fuzz_files import FILE_FAMILIES, mutate, shipped
from platoon_opt.study.fuzz_oracle import CASE_FILE, Case, Entry, Outcome, run_case, verdict
from platoon_opt.study.fuzz_report import markdown
from platoon_opt.study.machine import load_average, machine
from platoon_opt.study.output import write_atomic, write_json

FAMILIES = FILE_FAMILIES + ARGV_FAMILIES
DEFAULT_CASES = 10_000
CHUNK = 100
# Findings kept with their reproduction per chunk (all are counted).
KEPT = 20
FINDINGS = 1
# The allocators a mutated file runs under, with their weights (nmpc with a short horizon).
SOLVERS = {"iterative": 12, "dual": 2, "qp": 2, "cone": 1, "qp-projection": 1, "cone-projection": 1}
SOLVERS.update({"casadi-qp": 1, "nmpc": 1})
_PACKAGE = Path(__file__).resolve().parents[1]


@functools.cache
def code_version() -> str:
    """Hash of every source file of the package and of the shipped scenarios."""
    digest = hashlib.sha256()
    for path in sorted([*_PACKAGE.rglob("*.py"), *_PACKAGE.glob("scenario_files/*.toml")]):
        digest.update(f"{path.relative_to(_PACKAGE).as_posix()}\n".encode() + path.read_bytes())
    return digest.hexdigest()[:20]


def _file_argv(data: bytes, rng: random.Random) -> tuple[tuple[str, ...], str, int, bool]:
    """The command a mutated file runs under: ``simulate`` (one case in twelve ``compare``) for
    one to four steps of the file's own dt where it has a usable one, so that a case takes
    milliseconds; returns (argv, command, steps, figures)."""
    dt = 0.01
    try:
        value = tomllib.loads(data.decode("utf-8").removeprefix("\ufeff"))["simulation"]["dt"]
        if isinstance(value, (int, float)) and math.isfinite(value) and 1e-9 <= value <= 1e3:
            dt = float(value)
    except (UnicodeDecodeError, tomllib.TOMLDecodeError, KeyError, TypeError):
        pass  # the file is broken anyway: the CLI refuses it before any step
    steps = rng.randint(1, 4)
    tail = ["--duration", repr(steps * dt), "--out", "out"]
    figures = rng.random() < 0.05  # figures are most of a short run's time
    tail += [] if figures else ["--no-figures"]
    if rng.random() < 1 / 12:
        configs = ["m=0", *rng.sample(["dual", "qp", "m=2"], rng.randint(0, 1))]
        argv = ["compare", CASE_FILE, "--seeds", "1", "--solvers", *configs, "--workers", "1", *tail]
        return tuple(argv), "compare", steps, figures
    solver = rng.choices(list(SOLVERS), weights=list(SOLVERS.values()))[0]
    argv = ["simulate", CASE_FILE, "--solver", solver, *tail]
    if solver == "nmpc":
        argv += ["--option", "intervals=2", "--option", "resolve_every=2"]
    if rng.random() < 0.3:
        argv += ["--seed", str(rng.randint(0, 9))]
    return tuple(argv), "simulate", steps, figures


@functools.cache
def _texts() -> dict[str, str]:
    return shipped()


def build_case(family: str, rng: random.Random, index: int = 0) -> Case:
    """A case of ``family`` drawn from ``rng`` (``index`` only names it)."""
    if family in FILE_FAMILIES:
        base, mutation = mutate(family, rng, _texts())
        argv, command, steps, figures = _file_argv(mutation.data, rng)
        return Case(
            index, family, mutation.kind, mutation.note, argv, mutation.data, base, mutation.must_fail,
            True, command, "out", steps, figures,
        )  # fmt: skip
    args = arguments(family, rng)
    return Case(
        index, family, args.kind, " ".join(args.argv)[:200], args.argv, None, "", args.must_fail, False,
        args.command, args.out, args.steps, args.figures,
    )  # fmt: skip


def make_case(seed: int, index: int) -> Case:
    """Case ``index`` of seed ``seed`` (the same in every run and process)."""
    family = FAMILIES[index % len(FAMILIES)]
    return build_case(family, random.Random(f"platoon-opt-fuzz:{seed}:{index}"), index)


def reproduction(case: Case, outcome: Outcome) -> dict[str, Any]:
    """A finding with what it takes to rerun it: the argv and, for a file, its bytes."""
    record: dict[str, Any] = {
        "index": case.number,
        "family": case.family,
        "kind": case.kind,
        "note": case.note,
        "argv": list(case.argv),
        "problems": list(outcome.problems),
        "status": outcome.status,
        "stderr": outcome.stderr[-600:],
        "traceback": outcome.error[-3000:],
    }
    if case.file is not None:
        record["file_base64"] = base64.b64encode(case.file).decode()
    return record


def fuzz_chunk(seed: int, family: str, indices: list[int], entry: Entry) -> dict[str, Any]:
    """The record of one chunk: its cases (``indices``, all of ``family``) run and judged."""
    verdicts: Counter[str] = Counter()
    kinds: Counter[str] = Counter()
    findings: list[dict[str, Any]] = []
    seconds = []
    for index in indices:
        case = make_case(seed, index)
        outcome = run_case(case, entry)
        verdicts[verdict(outcome)] += 1
        kinds[f"{case.kind} -> {verdict(outcome)}"] += 1
        seconds.append(round(outcome.seconds, 5))
        if outcome.problems and len(findings) < KEPT:
            findings.append(reproduction(case, outcome))
    return {
        "family": family,
        "cases": len(indices),
        "verdicts": dict(verdicts),
        "kinds": dict(kinds),
        "seconds": seconds,
        "findings": findings,
    }


def run(
    out_dir: str | Path,
    entry: Entry,
    *,
    cases: int = DEFAULT_CASES,
    seed: int = 0,
    fresh: bool = False,
    stream: TextIO | None = None,
    command: str = "",
) -> dict[str, Any]:
    """Run cases 0 .. cases - 1 of ``seed`` through ``entry`` (``cli.main``), one chunk after
    another, and write ``out_dir/fuzz.json`` and ``fuzz.md``; returns fuzz.json's content."""
    out = Path(out_dir)
    cache = ResultCache(out, fresh=fresh)
    shared = {"seed": seed, "code": code_version(), "chunk": CHUNK}
    jobs = {
        (family, chunk): list(range(FAMILIES.index(family), cases, len(FAMILIES)))[
            chunk * CHUNK : (chunk + 1) * CHUNK
        ]
        for family in FAMILIES
        for chunk in range(math.ceil(len(range(FAMILIES.index(family), cases, len(FAMILIES))) / CHUNK))
    }

    def key(job: tuple[str, int]) -> str:
        return f"fuzz-chunks/{job[0]}/{job[1]:05d}"

    def stamp(job: tuple[str, int]) -> str:
        return fingerprint({**shared, "family": job[0], "indices": jobs[job]})

    started = time.perf_counter()
    done: dict[tuple[str, int], dict[str, Any]] = {}
    with Progress(cases, "fuzz", unit="cases", stream=stream) as progress:
        for job, indices in jobs.items():
            record = cache.load(key(job), stamp(job))
            if record is not None:
                progress.reuse(record["cases"])
            else:
                record = fuzz_chunk(seed, job[0], indices, entry)
                cache.store(key(job), stamp(job), record)
                progress.advance(record["cases"])
            done[job] = record
    result = {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine(),
        "load": load_average(),
        "command": command,
        **shared,
        "cases": cases,
        "reused": progress.reused,
        "wall_time": time.perf_counter() - started,
        "chunks": list(done.values()),
    }
    write_json(out / "fuzz.json", result)
    write_atomic(out / "fuzz.md", markdown(result))
    return result


def show_case(case: Case, seed: int = 0) -> str:
    """``case`` in words: its family, change, argument list and file."""
    lines = [
        f"case {case.number} of seed {seed}: {case.family} ({case.kind}): {case.note}",
        "argv: " + " ".join(_quoted(word) for word in ["platoon-opt", *case.argv]),
        f"expected: {'an error (exit 2)' if case.must_fail else 'a run or one line'}",
    ]
    if case.file is not None:
        lines.append(f"{CASE_FILE} (from {case.base}, {len(case.file)} bytes):")
        lines.append(case.file.decode("utf-8", errors="backslashreplace"))
    return "\n".join(lines)


def _quoted(word: str) -> str:
    plain = word and all(c.isalnum() or c in "-_=.,:/+" for c in word)
    return word if plain else repr(word)


# --- the command line ---------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser, default_out: Path) -> None:
    """The options of ``platoon-opt fuzz``."""
    parser.add_argument(
        "--cases", type=CASES, default=DEFAULT_CASES, help=f"cases in all (default {DEFAULT_CASES:,})"
    )
    parser.add_argument("--seed", type=SEED, default=0, help="case seed (default 0)")
    parser.add_argument("--out", default=str(default_out), help=f"output folder (default {default_out})")
    parser.add_argument("--fresh", action="store_true", help="rerun the chunks an earlier run finished")
    parser.add_argument("--show", type=SEED, metavar="INDEX", help="print case INDEX (argv and file)")


def command(args: argparse.Namespace, typed: str, entry: Entry) -> int:
    """Run ``platoon-opt fuzz`` with checked options; returns 0, ``FINDINGS`` if a case failed,
    or ``exits.stopped``'s status."""
    if args.show is not None:
        print(show_case(make_case(args.seed, args.show), args.seed))
        return 0
    try:
        result = run(args.out, entry, cases=args.cases, seed=args.seed, fresh=args.fresh, command=typed)
    except KeyboardInterrupt as stop:
        what, status = stopped(stop)
        note = f"finished chunks are in {args.out}/fuzz-chunks (the same command resumes)"
        print(f"\nplatoon-opt: {what}: {note}", file=sys.stderr)
        return status
    found = sum(chunk["verdicts"].get("finding", 0) for chunk in result["chunks"])
    print(f"{args.cases:,} cases, {found} findings; wrote {args.out}/fuzz.json and fuzz.md")
    return FINDINGS if found else 0
