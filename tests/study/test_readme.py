"""The README's library examples run as written and print what the README shows."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[2] / "README.md"


EXAMPLES = re.findall(r"```python\n(.*?)```\n\nprints\n\n```text\n(.*?)```", README.read_text(), flags=re.S)


def test_the_readme_has_its_examples():
    assert len(EXAMPLES) == 2, "README's python examples, each followed by its output"


@pytest.mark.parametrize("code, shown", EXAMPLES)
def test_readme_library_example_prints_what_the_readme_shows(code, shown, capsys):
    exec(compile(code, str(README), "exec"), {})
    assert capsys.readouterr().out == shown
