"""The README's library example runs as written and prints what the README shows."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_library_example_prints_what_the_readme_shows(capsys):
    text = README.read_text()
    example = re.search(r"```python\n(.*?)```\n\nprints\n\n```text\n(.*?)```", text, flags=re.S)
    assert example, "README has no python example followed by its output"
    code, shown = example.groups()
    exec(compile(code, str(README), "exec"), {})
    assert capsys.readouterr().out == shown
