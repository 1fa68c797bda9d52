"""Finished work on disk, so that a long study resumes where it stopped.

Each finished item (a closed-loop run of the harness, a chunk of the soak) is one JSON file,
written atomically as soon as it finishes, holding its record and the fingerprint of
everything that determined it (inputs and code). A later call reuses the record only if its own
fingerprint for the item is the same; anything else is computed again and overwritten.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from platoon_opt.study.output import write_atomic, write_json


def fingerprint(value: Any) -> str:
    """A short hash of a JSON-ready value (keys sorted; other objects by ``str``)."""
    text = json.dumps(value, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


class ResultCache:
    """Records under ``folder``, one ``<key>.json`` each (``key`` may hold slashes), and optional
    binary attachments ``<key><suffix>`` beside them. ``folder=None`` keeps nothing; ``fresh``
    ignores what is there (it is overwritten)."""

    def __init__(self, folder: str | Path | None, *, fresh: bool = False) -> None:
        self.folder = None if folder is None else Path(folder)
        self.fresh = fresh

    def path(self, key: str, suffix: str = ".json") -> Path | None:
        """Where the record (or attachment) of ``key`` lives; None without a folder."""
        return None if self.folder is None else self.folder / f"{key}{suffix}"

    def load(self, key: str, fingerprint: str) -> dict[str, Any] | None:
        """The record of ``key`` if one was stored with ``fingerprint``, else None."""
        path = self.path(key)
        if path is None or self.fresh:
            return None
        try:
            record = json.loads(path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None
        if record.get("fingerprint") != fingerprint:
            return None
        # JSON has no infinity: write_json stores it as a string.
        return {k: float(v) if v in ("inf", "-inf", "nan") else v for k, v in record.items()}

    def store(
        self,
        key: str,
        fingerprint: str,
        record: Mapping[str, Any],
        attachments: Mapping[str, bytes] | None = None,
    ) -> None:
        """Write ``record`` (with ``fingerprint`` added) and its ``attachments`` (suffix -> bytes).
        The attachments go first, so that a stored record always has them."""
        if self.folder is None:
            return
        for suffix, data in (attachments or {}).items():
            write_atomic(self.folder / f"{key}{suffix}", data)
        write_json(self.folder / f"{key}.json", {**record, "fingerprint": fingerprint})
