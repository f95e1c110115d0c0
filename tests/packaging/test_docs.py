"""The documentation as a reference: the options page is the registry's, links resolve, no page
narrates work history (docs/index.md)."""
import os
import re

import pytest

from vesflow import cli, options

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
DOCS = os.path.join(ROOT, "docs")
STUDY = os.path.join(DOCS, "study")          # generated result folders, not pages


def pages():
    """Every hand-written page: docs/**/*.md outside docs/study/, and the README."""
    out = [os.path.join(ROOT, "README.md")]
    for d, dirs, files in os.walk(DOCS):
        if os.path.commonpath([d, STUDY]) == STUDY:
            continue
        out += [os.path.join(d, f) for f in sorted(files) if f.endswith(".md")]
    return out


def rel(path):
    return os.path.relpath(path, ROOT)


def read(path):
    with open(path, encoding="utf-8") as f:
        return f.read()


def run_help(capsys):
    assert cli.main(["run", "-help"]) == 0
    return capsys.readouterr().out


# ---------------------------------------------------------------------------------- options
def test_options_page_is_the_generated_one():
    page = read(os.path.join(DOCS, "reference", "options.md"))
    assert page == options.markdown_text(), (
        "docs/reference/options.md is stale: python -m vesflow.options --markdown > docs/reference/options.md")


def test_every_option_of_run_help_is_on_the_options_page(capsys):
    names = re.findall(r"^  (-\w+) ", run_help(capsys), flags=re.M)
    assert len(names) == len(options.REGISTRY) and "-ves_p" in names and "-ts_type" in names
    page = read(os.path.join(DOCS, "reference", "options.md"))
    missing = [n for n in names if f"| `{n}` |" not in page]
    assert not missing, f"options in `vesflow run -help` missing from docs/reference/options.md: {missing}"


# ---------------------------------------------------------------------------------- links
LINK = re.compile(r"\]\(([^)\s]+)\)")                      # [text](target), ![alt](target)
CITED = re.compile(r"(?<![\w/.])(docs/[\w./-]+\.(?:md|png|csv|txt))")   # docs/... paths named in text


def link_targets(path):
    """(target as written, resolved path) of every local link and docs/ path cited in a page."""
    text = read(path)
    prose = re.sub(r"```.*?```", "", text, flags=re.S)              # links are not in code:
    prose = re.sub(r"^(    |\t).*$", "", prose, flags=re.M)          # fenced, indented
    prose = re.sub(r"`[^`\n]*`", "", prose)                           # or inline
    for t in LINK.findall(prose):
        if re.match(r"[a-z]+:", t) or t.startswith("#"):
            continue
        yield t, os.path.normpath(os.path.join(os.path.dirname(path), t.split("#")[0]))
    for t in CITED.findall(text):
        yield t, os.path.join(ROOT, t)


def test_every_link_between_docs_pages_resolves():
    broken = [f"{rel(p)}: {t}" for p in pages() for t, target in link_targets(p) if not os.path.exists(target)]
    assert not broken, "links to missing files:\n" + "\n".join(broken)


def test_docs_paths_cited_in_the_package_exist():
    broken = []
    for d, _, files in os.walk(os.path.join(ROOT, "vesflow")):
        for f in files:
            if f.endswith((".py", ".pyx", ".h")):
                p = os.path.join(d, f)
                broken += [f"{rel(p)}: {t}" for t in CITED.findall(read(p)) if not os.path.exists(os.path.join(ROOT, t))]
    assert not broken, "the package cites missing docs pages:\n" + "\n".join(broken)


def test_every_page_is_reachable_from_the_index():
    index = os.path.join(DOCS, "index.md")
    linked = {target for _, target in link_targets(index)}
    orphans = [rel(p) for p in pages() if p not in linked and p != index and not p.endswith("README.md")]
    assert not orphans, f"pages not linked from docs/index.md: {orphans}"


# ---------------------------------------------------------------------------------- history
HISTORY = [
    (re.compile(r"\b(sessions?|stop \d+|waves?)\b", re.I), "work period"),
    (re.compile(r"\bcommits?\b[^\n]{0,40}?\b[0-9a-f]{7,40}\b|\b[0-9a-f]{7,40}\b[^\n]{0,20}?\bcommit\b", re.I),
     "commit hash"),
    (re.compile(r"\b(main|branch|merged?)\s+[0-9a-f]{7,40}\b"), "commit hash"),
    (re.compile(r"\bload (average )?(of |at |about |was |~)?\d", re.I), "machine-load reading"),
    (re.compile(r"\bissues? \d+\b", re.I), "issue number"),
    (re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b"), "date"),
    (re.compile(r"\b(before|after) (the )?(issue|merge|wave|session)\b", re.I), "before/after narration"),
]


def history_markers(text):
    found = []
    for n, line in enumerate(text.splitlines(), 1):
        for rx, what in HISTORY:
            m = rx.search(line)
            if m:
                found.append(f"{n}: {what}: {m.group(0)!r}")
    return found


def test_history_markers_are_recognized():
    assert history_markers("## Speed: fourth session")
    assert history_markers("the first study's code (commit\n171b0a2) and main 65ff6db")[0].startswith("2")
    assert history_markers("re-run at load 3-5 on the shared machine")
    assert history_markers("stop 4: the post-step")
    assert not history_markers("the p = 12 pair, 30 steps, 0.14 s per step (benchmarks/step_cost.py --p 12)")


def test_no_page_narrates_work_history():
    bad = [f"{rel(p)}:{m}" for p in pages() for m in history_markers(read(p))]
    assert not bad, "history belongs in CHANGELOG.md and git:\n" + "\n".join(bad)


@pytest.mark.parametrize("name", ["far_field.md", "accuracy_cost.md"])
def test_long_explanations_stay_short(name):
    lines = read(os.path.join(DOCS, "explanation", name)).count("\n")
    assert lines <= 400, f"docs/explanation/{name}: {lines} lines (at most 400)"


def test_no_page_repeats_a_heading():
    dup = []
    for p in pages():
        heads = re.findall(r"^#+ .*$", re.sub(r"```.*?```", "", read(p), flags=re.S), flags=re.M)
        dup += [f"{rel(p)}: {h}" for h in sorted(set(heads)) if heads.count(h) > 1]
    assert not dup, "headings repeated within a page:\n" + "\n".join(dup)
