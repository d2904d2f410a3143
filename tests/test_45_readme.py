"""The user's guide holds: README.md and docs/*.md run, link and list as written.

Oracles: the documents themselves and the checkout.

- Every ```python block of README.md and docs/*.md (de-indented where it
  sits in a list) is written to a file and run by this Python in a fresh
  folder that has the repository's ``scenes/`` (the snippets name scene
  files relative to the repository's root, where the documents' commands
  run); it must exit with status 0 and write the files it names. There is
  no way to skip a Python block: a block that is not meant to run (a
  fragment, pseudo-code) takes another language tag (```text); a fence
  such as ```python skip or ```py is refused, so none is left out unseen.
- README.md is a user's guide of at most 450 lines; the reference, the
  gradient method, frame sequences and measurements live in docs/.
- Every scene of ``scenes/*.xml`` (the files in the checkout) is named in a
  row of README.md's tables.
- Every relative link and image of README.md and docs/*.md names a file or
  folder of the checkout, and a ``#anchor`` names a heading of its target
  Markdown file, by GitHub's rule for heading anchors (lower case;
  characters other than letters, digits, spaces, hyphens and underscores
  dropped; spaces to hyphens; a repeated heading gets ``-1``, ``-2``, ...).
"""
import glob
import os
import re
import subprocess
import sys
import textwrap

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
DOCS = [README] + sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))
README_MAX_LINES = 450

FENCE = re.compile(r"^( *)(`{3,})([^\n`]*)\n(.*?)^\1\2[ \t]*$", re.S | re.M)


def read(path):
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def fences(text):
    """(language tag, de-indented code) of each fenced block of `text`."""
    return [(tag.strip(), textwrap.dedent(code)) for _, _, tag, code in FENCE.findall(text)]


def snippets():
    """(id, code) of every ```python block of the documents, in order."""
    found = []
    for path in DOCS:
        blocks = [code for tag, code in fences(read(path)) if tag == "python"]
        name = os.path.relpath(path, ROOT)
        found += [(f"{name}:{i}", code) for i, code in enumerate(blocks)]
    return found


SNIPPETS = snippets()

#: What a snippet writes, by a line it contains.
WRITES = {
    'write_bitmap("shapes.png"': ["shapes.png"],
    "render_frames(": [f"out/ease_{k:04d}.{ext}" for k in range(4) for ext in ("exr", "png")]
    + ["out/ease.mp4"],
}


def test01_the_documents_have_their_snippets():
    """The README shows a render through Mitsuba, scene parameters and a
    ray query; the docs a gradient, frame sequences and many primitives."""
    by_file = {}
    for sid, code in SNIPPETS:
        by_file.setdefault(sid.rsplit(":", 1)[0], []).append(code)
    readme = by_file.get("README.md", [])
    assert any("mi.render(" in s for s in readme)
    assert any("mi.traverse(" in s for s in readme)
    assert any("lgshape.Surface(" in s for s in readme)
    assert any("dr.backward(" in s for s in by_file.get(os.path.join("docs", "gradients.md"), []))
    assert any("render_frames(" in s for s in by_file.get(os.path.join("docs", "frames.md"), []))
    assert any("primitives" in s for s in by_file.get(os.path.join("docs", "plugins.md"), []))


@pytest.mark.parametrize("code", [c for _, c in SNIPPETS], ids=[i for i, _ in SNIPPETS])
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


@pytest.mark.parametrize("path", DOCS, ids=[os.path.relpath(p, ROOT) for p in DOCS])
def test03_no_python_block_is_left_out(path):
    """A fence whose tag starts with "py" is exactly ```python (run by
    test02); anything else there would be skipped without a word."""
    tags = [tag for tag, _ in fences(read(path)) if tag.lower().startswith("py")]
    assert all(tag == "python" for tag in tags), tags


def test04_readme_is_a_guide():
    lines = read(README).count("\n")
    assert lines <= README_MAX_LINES, f"README.md has {lines} lines (at most {README_MAX_LINES})"


def test05_every_scene_is_listed():
    scenes = sorted(os.path.basename(p) for p in glob.glob(os.path.join(ROOT, "scenes", "*.xml")))
    assert scenes, "no scenes/*.xml in the checkout"
    rows = [line for line in read(README).splitlines() if line.startswith("|")]
    missing = [s for s in scenes if not any(s in row for row in rows)]
    assert not missing, f"scenes not in README.md's tables: {missing}"


def slug(heading):
    """GitHub's anchor of a heading's text."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text):
    """The heading anchors of a Markdown text (outside fenced blocks)."""
    seen, out = {}, set()
    for line in FENCE.sub("", text).splitlines():
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        base = slug(m.group(1))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(text):
    """Targets of the inline links and images of a Markdown text, outside
    fenced blocks and inline code."""
    text = FENCE.sub("", text)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)


def test06_slug_follows_github():
    """The anchor rule on headings of these documents (GitHub's anchors,
    read off its rendering of them)."""
    assert slug("What counts as a surface: the contract for any f") == \
        "what-counts-as-a-surface-the-contract-for-any-f"
    assert slug("`lg_prb`: path replay backpropagation") == "lg_prb-path-replay-backpropagation"
    assert slug("Scene parameters (mi.traverse)") == "scene-parameters-mitraverse"
    assert slug("The user guide's figures") == "the-user-guides-figures"
    assert anchors("# A\n## A\n```text\n# A\n```\n### A\n") == {"a", "a-1", "a-2"}


@pytest.mark.parametrize("path", DOCS, ids=[os.path.relpath(p, ROOT) for p in DOCS])
def test07_relative_links_resolve(path):
    text = read(path)
    broken = []
    for target in links(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):       # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        dest = os.path.normpath(os.path.join(os.path.dirname(path), file_part)) if file_part \
            else path
        if not os.path.exists(dest):
            broken.append(f"{target} (no file {os.path.relpath(dest, ROOT)})")
        elif anchor and dest.endswith(".md") and anchor not in anchors(read(dest)):
            broken.append(f"{target} (no heading #{anchor} in {os.path.relpath(dest, ROOT)})")
    assert not broken, f"{os.path.relpath(path, ROOT)}: broken links: {broken}"
