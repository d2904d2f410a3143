"""Every Python snippet of README.md runs as written, pasted into a file.

Oracle: the README itself. Each ```python block (de-indented where it sits
in a list) is written to a file and run by this Python in a fresh folder
that has the repository's ``scenes/`` (the snippets name scene files
relative to the repository's root, where the README's commands run); it
must exit with status 0 and write the files it names.
"""
import os
import re
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def snippets():
    with open(os.path.join(ROOT, "README.md")) as fh:
        text = fh.read()
    blocks = re.findall(r"^( *)```python\n(.*?)^\1```", text, re.S | re.M)
    return [textwrap.dedent(code) for _, code in blocks]


SNIPPETS = snippets()

#: What a snippet writes, by a line it contains.
WRITES = {
    'write_bitmap("shapes.png"': ["shapes.png"],
    "render_frames(": [f"out/ease_{k:04d}.{ext}" for k in range(4) for ext in ("exr", "png")]
    + ["out/ease.mp4"],
}


def test01_the_readme_has_its_snippets():
    assert len(SNIPPETS) >= 5
    assert any("render_frames(" in s for s in SNIPPETS)


@pytest.mark.parametrize("code", SNIPPETS, ids=[f"snippet{i}" for i in range(len(SNIPPETS))])
def test02_snippet_runs_as_written(code, tmp_path):
    os.symlink(os.path.join(ROOT, "scenes"), tmp_path / "scenes")
    (tmp_path / "snippet.py").write_text(code)
    run = subprocess.run([sys.executable, "snippet.py"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
    for marker, files in WRITES.items():
        if marker in code:
            for name in files:
                assert (tmp_path / name).is_file(), name
