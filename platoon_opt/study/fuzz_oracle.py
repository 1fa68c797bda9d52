"""Running one fuzz case through ``platoon_opt.study.cli.main`` in this process, and judging it.

A case runs in a fresh temporary folder (its working directory, holding the mutated scenario as
``case.toml``, a file that is no scenario and a folder), with stdout, stderr and Python warnings
captured. It passes when it ends

* in exit 0 with a sane run: the files a run writes, metrics finite where they should be, the
  steps asked for, nothing on stderr but ``platoon-opt: warning:`` lines, no RuntimeWarning; or
* in exit 2 with exactly one stderr line ``platoon-opt: error: ...`` that names what was wrong:
  for a scenario file the file, and the key and the value as the file has them (checked against
  the file: ``scenario_message``), else a flag, option or word of the argument list; or
* in exit 3 for a ``--strict`` run, with one line naming the allocator that failed;

and fails on a traceback, any other exit status, exit 0 for input that breaks a documented rule,
exit 2 for input that breaks none (argument lists only), or a line that names nothing.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import signal
import tempfile
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

from platoon_opt.scenario_checks import SCHEMA, show
from platoon_opt.scenarios import tomllib
from platoon_opt.study.exits import INTERRUPTED, TERMINATED, Terminated
from platoon_opt.study.fuzz_argv import EXISTING_FILE, EXISTING_FOLDER

CASE_FILE = "case.toml"
ERROR, WARNING = "platoon-opt: error: ", "platoon-opt: warning: "
# A case that runs longer than this (s) is stopped and fails: every case is meant to be short.
TIMEOUT = 120.0


class Case(NamedTuple):
    """One fuzz case: an argument list and, for a file family, the mutated scenario file.

    Attributes:
        number: the case's index in its run (``fuzz.make_case``).
        family: the mutation family.
        kind: the family's variant ("type-swap:str-for-number").
        note: what was changed, in words.
        argv: the arguments after ``platoon-opt``.
        file: the bytes of ``case.toml``, or None.
        base: the shipped scenario the file was made from ("" for none).
        must_fail: docs/scenarios.md or docs/cli.md make the input an error (exit 2).
        strict_either: exit 2 is also right (a file family, whose validity the fuzzer does not
            decide); False for an argument list that breaks no rule, which must run.
        command, out, steps, figures: the run expected if the input is valid (``Arguments``).
    """

    number: int
    family: str
    kind: str
    note: str
    argv: tuple[str, ...]
    file: bytes | None
    base: str
    must_fail: bool
    strict_either: bool
    command: str
    out: str
    steps: int
    figures: bool


class Outcome(NamedTuple):
    """What a case did and why it failed (``problems``; empty when it passed)."""

    status: int | None
    stdout: str
    stderr: str
    error: str
    warnings: tuple[str, ...]
    seconds: float
    problems: tuple[str, ...]


class CaseTimeout(BaseException):
    """A case ran past ``TIMEOUT`` (a BaseException, so that no handler of the CLI takes it)."""


@contextlib.contextmanager
def _alarm(seconds: float) -> Iterator[None]:
    """Raise ``CaseTimeout`` after ``seconds`` (in the main thread only: signals need it)."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "setitimer"):
        yield
        return

    def expire(signum: int, frame: Any) -> None:
        raise CaseTimeout

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


# The command line's entry point: ``platoon_opt.study.cli.main`` (which imports the fuzzer, so
# the fuzzer is handed it rather than importing it).
Entry = Callable[[list[str]], int]


def run_case(case: Case, entry: Entry, timeout: float = TIMEOUT) -> Outcome:
    """Run ``case`` through ``entry`` (``cli.main``) in a fresh folder and judge it.

    Raises:
        KeyboardInterrupt: the case was interrupted (Ctrl-C reached the CLI, exit 130), or
            ``Terminated`` (SIGTERM, exit 143).
    """
    with tempfile.TemporaryDirectory(prefix="platoon-opt-fuzz-") as name:
        folder = Path(name)
        (folder / EXISTING_FILE).write_text("not a scenario\n")
        (folder / EXISTING_FOLDER).mkdir()
        if case.file is not None:
            (folder / CASE_FILE).write_bytes(case.file)
        stdout, stderr = io.StringIO(), io.StringIO()
        previous = os.getcwd()
        status: int | None = None
        error = ""
        start = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                os.chdir(folder)
                with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
                    with _alarm(timeout):
                        status = entry(list(case.argv))
            except CaseTimeout:
                error = f"timeout: still running after {timeout:g} s"
            except KeyboardInterrupt:
                raise
            except BaseException:  # a traceback is what the fuzzer looks for
                error = traceback.format_exc()
            finally:
                os.chdir(previous)
        seconds = time.perf_counter() - start
        if status == INTERRUPTED:
            raise KeyboardInterrupt
        if status == TERMINATED:
            raise Terminated
        shown = tuple(f"{w.category.__name__}: {w.message} ({Path(w.filename).name})" for w in caught)
        problems = judge(case, status, stderr.getvalue(), error, shown, folder)
        return Outcome(status, stdout.getvalue(), stderr.getvalue(), error, shown, seconds, tuple(problems))


def judge(
    case: Case,
    status: int | None,
    stderr: str,
    error: str,
    caught: tuple[str, ...],
    folder: Path,
) -> list[str]:
    """Why the case failed (empty: it passed); see the module's docstring."""
    if error:
        last = error.strip().splitlines()[-1]
        return [f"traceback: {last}" if not error.startswith("timeout") else error]
    lines = stderr.strip().splitlines()
    if status == 2:
        if len(lines) != 1 or not lines[0].startswith(ERROR):
            return [f"exit 2 with {len(lines)} stderr lines: {stderr.strip()[:300]!r}"]
        problems = [f"exit 2 with a warning: {w}" for w in caught]
        if not case.must_fail and not case.strict_either:
            problems.append("exit 2 for input that breaks no documented rule")
        named = names_what(case, lines[0][len(ERROR) :])
        return problems + ([named] if named else [])
    if status == 3 and "--strict" in case.argv:
        if len(lines) == 1 and lines[0].startswith(f"{ERROR}allocator "):
            return []
        return [f"exit 3 without one line naming the allocator: {stderr.strip()[:300]!r}"]
    if status != 0:
        return [f"exit status {status}: {stderr.strip()[:300]!r}"]
    problems = []
    if case.must_fail:
        problems.append(f"exit 0 for input that breaks a documented rule ({case.note})")
    stray = [line for line in lines if not line.startswith(WARNING)]
    if stray:
        problems.append(f"exit 0 with stderr other than warnings: {stray[0][:200]!r}")
    problems += [f"exit 0 with {w}" for w in caught if w.startswith(("RuntimeWarning", "UserWarning"))]
    return problems + sane_run(case, folder)


def names_what(case: Case, message: str) -> str | None:
    """None if ``message`` names what was wrong, else why not: an error about the scenario file
    names the file, the key and the value (``scenario_message``); any other names a flag, option,
    name or value of the argument list (a word of two characters or more, any word quoted, or a
    word the message starts with, as ``.: is a folder``)."""
    if message.startswith(f"{CASE_FILE}: ") and case.file is not None:
        return scenario_message(message[len(CASE_FILE) + 2 :], case.file)
    text = re.sub(r" \(see platoon-opt[\w -]* --help\)$", "", message)
    words = list(case.argv[1:]) if case.argv and not case.argv[0].startswith("-") else list(case.argv)
    stray = re.fullmatch(r"unrecognized arguments: (.*)", text)
    if stray:
        return None if set(stray.group(1).split()) <= set(case.argv) else f"no such arguments: {text!r}"
    tokens = set()
    for word in words:
        tokens.update([word, *re.split(r"[=:,]", word)])
    named = any((len(t) >= 2 and t in text) or repr(t) in text or text.startswith(f"{t}: ") for t in tokens)
    required = ("the following arguments are required", "argument command: invalid choice")
    if named or text.startswith(required):
        return None
    return f"the error names no flag, option or value of the arguments: {message!r}"


def _segments(path: str) -> list[str | int] | None:
    """A key path as written in a message (``a.b[2]."odd key"``) as its keys and indices."""
    parts: list[str | int] = []
    i = 0
    while i < len(path):
        if path[i] == '"':
            try:
                key, i = json.JSONDecoder().raw_decode(path, i)
            except ValueError:
                return None
            parts.append(key)
        elif path[i] == "[":
            index = re.match(r"\[(\d+)\]", path[i:])
            if index is None:
                return None
            parts.append(int(index.group(1)))
            i += index.end()
        else:
            bare = re.match(r"[A-Za-z0-9_-]+", path[i:])
            if bare is None:
                return None
            parts.append(bare.group(0))
            i += bare.end()
        if i < len(path) and path[i] == ".":
            i += 1
    return parts


def _resolve(table: Any, path: str) -> tuple[bool, Any]:
    """The value at key path ``path`` of ``table`` (found, value)."""
    parts = _segments(path)
    if parts is None:
        return False, None
    node = table
    for part in parts:
        if isinstance(part, int) and isinstance(node, list) and part < len(node):
            node = node[part]
        elif isinstance(part, str) and isinstance(node, dict) and part in node:
            node = node[part]
        else:
            return False, None
    return True, node


def _schema_key(path: str) -> bool:
    """Whether ``path`` is a key docs/scenarios.md defines (one with a default, when absent)."""
    node: Any = SCHEMA
    for part in re.sub(r"\[\d+\]", "", path).split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def scenario_message(text: str, data: bytes) -> str | None:
    """None if ``text`` (an error about the scenario file, after its name) is one of the shapes of
    ``platoon_opt.scenario_checks`` and right about ``data``; else why not."""
    try:
        decoded = data.decode("utf-8").removeprefix("\ufeff")
    except UnicodeDecodeError:
        return None if text.startswith("not UTF-8 text: bytes ") else f"the file is not UTF-8, but: {text!r}"
    try:
        table = tomllib.loads(decoded)
    except tomllib.TOMLDecodeError:
        ok = text.startswith("not valid TOML: ") and ("line" in text or "end of document" in text)
        return None if ok else f"the file is not TOML, but: {text!r}"
    match = re.fullmatch(r"missing key (\S+)( \(.*\))?", text)
    if match:
        return None if not _resolve(table, match.group(1))[0] else f"not missing: {text!r}"
    match = re.fullmatch(r"unknown key (.*?) = (.*); valid: (.+)", text, re.DOTALL)
    if match:
        found, value = _resolve(table, match.group(1))
        return None if found and show(value) == match.group(2) else f"no such key and value: {text!r}"
    match = re.fullmatch(r"(\S+) must be (.+), got (.*)", text, re.DOTALL)
    if match:
        found, value = _resolve(table, match.group(1))
        if found and show(value) == match.group(3):
            return None
        if not found and _schema_key(match.group(1)):
            return None  # a default broke a rule that involves another key
        return f"the key or the value is not the file's: {text!r}"
    return f"the error does not name a key and its value: {text!r}"


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def sane_run(case: Case, folder: Path) -> list[str]:
    """What is wrong with the files of a run that exited 0 (empty: nothing)."""
    out = folder / case.out
    if case.command == "simulate":
        return _simulate_files(case, out)
    if case.command == "compare":
        return _study_files(case, out)
    return [f"exit 0 where no run was expected ({case.kind})"]


def verdict(outcome: Outcome) -> str:
    """A case's class: "finding" (it failed), else "run" (exit 0), "error" (exit 2, one line) or
    "strict stop" (exit 3, a ``--strict`` run whose allocator failed)."""
    if outcome.problems:
        return "finding"
    return {0: "run", 2: "error", 3: "strict stop"}[outcome.status or 0]


def _simulate_files(case: Case, out: Path) -> list[str]:
    try:
        metrics = json.loads((out / "metrics.json").read_text())
        rows = list(csv.reader(io.StringIO((out / "timeseries.csv").read_text())))
    except (OSError, ValueError) as error:
        return [f"simulate exit 0 without its files: {error}"]
    problems = []
    if case.steps and metrics.get("steps") != case.steps:
        problems.append(f"{metrics.get('steps')} steps, asked for {case.steps}")
    for key in ("mean_position", "mean_position_after_transient", "min_unit_distance"):
        if not _finite(metrics.get(key)):
            problems.append(f"metrics.json: {key} = {metrics.get(key)!r}")
    components = [key for key in metrics if key.startswith(("var_", "cov_")) and "after" not in key]
    problems += [f"metrics.json: {key} = {metrics[key]!r}" for key in components if not _finite(metrics[key])]
    if not (_finite(metrics.get("min_clearance")) or metrics.get("min_clearance") == "inf"):
        problems.append(f"metrics.json: min_clearance = {metrics.get('min_clearance')!r}")
    if len(rows) != metrics.get("steps", -1) + 2:
        problems.append(f"timeseries.csv has {len(rows)} rows for {metrics.get('steps')} steps")
    status = rows[0].index("status") if rows and "status" in rows[0] else -1
    for row in rows[1:]:
        bad = [cell for i, cell in enumerate(row) if i != status and cell.lower() in ("nan", "inf", "-inf")]
        if bad:
            problems.append(f"timeseries.csv holds {bad[0]}")
            break
    figures = [(out / name).is_file() for name in ("trajectory.png", "errors.png")]
    if case.figures and not all(figures):
        problems.append("figures asked for, not written")
    if not case.figures and any(figures):
        problems.append("--no-figures, figures written")
    return problems


def _study_files(case: Case, out: Path) -> list[str]:
    try:
        results = json.loads((out / "results.json").read_text())
        (out / "report.md").read_text()
    except (OSError, ValueError) as error:
        return [f"{case.command} exit 0 without its files: {error}"]
    problems = []
    for run in results.get("runs", []):
        if run["variant"] == "base" and case.steps and run["steps"] != case.steps:
            problems.append(f"run {run['key']}: {run['steps']} steps, asked for {case.steps}")
        for key in ("mean_position", "mean_position_after_transient", "var_x", "var_y"):
            if key in run and not _finite(run[key]):
                problems.append(f"run {run['key']}: {key} = {run[key]!r}")
    if not results.get("runs"):
        problems.append("results.json holds no runs")
    if case.figures != (out / "figures").is_dir():
        problems.append(f"figures asked for: {case.figures}, figures/ written: {not case.figures}")
    return problems[:5]
