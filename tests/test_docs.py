"""The documentation cannot drift from the code.

- ``docs/parameters.md`` is exactly what ``tools/gen_docs.py`` generates from the parameter metadata.
- Every Python block of ``docs/plugin-guide.md`` runs, in order, as one script.
- ``docs/results.md`` names every key that ``RunResult.to_dict()`` (and the evaluation JSON) emits.
- ``docs/data-formats.md`` has a section per built-in reader.
- Every relative link in ``docs/`` resolves, anchors included, and ``docs/index.md`` links every page.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import re
import subprocess
import sys
import types
from importlib.metadata import distribution
from pathlib import Path

import pytest

from artclass_core import Config, Pipeline, PipelineParams, describe, load_registry, open_sequences
from artclass_core.evaluate import evaluate

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
GEN_DOCS = ROOT / "tools" / "gen_docs.py"


def _load_gen_docs():
    spec = importlib.util.spec_from_file_location("artclass_gen_docs", GEN_DOCS)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


gen_docs = _load_gen_docs()


@pytest.fixture(scope="module")
def builtin():
    return gen_docs.builtin_registry()


@pytest.fixture(scope="module")
def small_sequence(rendered) -> Path:
    """A small labelled sequence with masks and per-frame truth, rendered by the generator."""
    return rendered("laptop", "articulate", n_frames=8, seed=3, width=160, height=120)


# -- parameters.md ----------------------------------------------------------------------------------


def test_parameters_md_is_up_to_date(builtin):
    committed = (DOCS / "parameters.md").read_text()
    assert committed == gen_docs.render(builtin), (
        "docs/parameters.md is out of date: run `python tools/gen_docs.py` and commit the result"
    )


def test_generator_covers_every_builtin_parameter(builtin):
    text = gen_docs.render(builtin)
    names = sorted(ep.name for ep in distribution("artclass").entry_points if ep.group == "artclass")
    assert names, "the artclass distribution declares no entry points"
    for spec in describe(PipelineParams):
        assert f"| `{spec.name}` | {spec.symbol} |" in text
    n = 0
    for kind, plugins in builtin.plugins.items():
        for name, info in plugins.items():
            assert f"### `{name}`" in text, f"{kind} {name} missing"
            for spec in describe(info.cls.Params):
                assert re.search(
                    rf"^\| `{spec.name}` \|.*\| {re.escape(gen_docs._cell(spec.help))} \|$", text, re.M
                ), f"{kind} {name}: parameter {spec.name} missing"
                n += 1
    assert n >= 10


def test_generator_leaves_third_party_plugins_out(builtin):
    """Only the artclass distribution's plugins are documented, whatever else is installed."""
    from types import SimpleNamespace

    from artclass_core import hookimpl
    from artclass_plugins.rules.paper import PaperRule

    class Outsider(PaperRule):
        name = "outsider_rule"

    @hookimpl
    def register_rules(register):
        register(Outsider)

    everything = load_registry(extra_plugins=(SimpleNamespace(register_rules=register_rules),))
    assert "outsider_rule" in gen_docs.render(everything)  # render() documents what it is given
    assert "outsider_rule" not in gen_docs.render(builtin)


@pytest.mark.slow
def test_gen_docs_check_command(tmp_path):
    ok = subprocess.run([sys.executable, str(GEN_DOCS), "--check"], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    stale = tmp_path / "parameters.md"
    stale.write_text((DOCS / "parameters.md").read_text().replace("Frame skip", "Frame skipping"))
    bad = subprocess.run(
        [sys.executable, str(GEN_DOCS), "--check", "--output", str(stale)], capture_output=True, text=True
    )
    assert bad.returncode == 1
    assert "out of date: run `python tools/gen_docs.py`" in bad.stderr
    written = subprocess.run(
        [sys.executable, str(GEN_DOCS), "--output", str(stale)], capture_output=True, text=True
    )
    assert written.returncode == 0 and stale.read_text() == (DOCS / "parameters.md").read_text()


# -- plugin-guide.md --------------------------------------------------------------------------------


@pytest.mark.slow
def test_plugin_guide_examples_run(capsys, monkeypatch):
    text = (DOCS / "plugin-guide.md").read_text()
    blocks = re.findall(r"^```python\n(.*?)^```", text, flags=re.M | re.S)
    assert len(blocks) >= 7
    # One fresh module, as if the blocks were pasted into a file (dataclasses look their module up).
    module = types.ModuleType("artclass_plugin_guide")
    monkeypatch.setitem(sys.modules, module.__name__, module)
    for n, block in enumerate(blocks, 1):
        exec(
            compile(block, f"docs/plugin-guide.md (python block {n})", "exec", dont_inherit=True),
            module.__dict__,
        )
    out = capsys.readouterr().out
    assert "laptop: 8 frames, 160x120" in out  # the `frames` command ran
    assert module.result.plugins["registrar"] == "numpy_icp"


# -- results.md -------------------------------------------------------------------------------------


def _documented(key: str, text: str) -> bool:
    return f"`{key}`" in text


@pytest.mark.slow
def test_results_md_names_every_key(small_sequence):
    registry = load_registry()
    text = (DOCS / "results.md").read_text()
    seq = open_sequences(registry, small_sequence)[0]
    result = Pipeline(registry, Config(pipeline=PipelineParams(k=2))).run(seq).to_dict()
    paper = (
        Pipeline(registry, dataclasses.replace(Config.paper(), pipeline=PipelineParams(k=2)))
        .run(seq)
        .to_dict()
    )
    json.dumps(result)  # JSON-ready as documented
    decided = next(p for p in result["pairs"] if p.get("motions"))
    pair = next(p for p in paper["pairs"] if any("fitness" in c for c in p["cells"]))
    cell = next(c for c in pair["cells"] if "fitness" in c)
    groups = {
        "top level": result,
        "sequence": result["sequence"],
        "pairs[]": {**pair, **decided},
        "pairs[].info (dense)": decided["info"],
        "motions[]": decided["motions"][0],
        "cells[]": cell,
        "timing_s": result["timing_s"],
        "params": result["params"],
        "plugins": result["plugins"],
        "frames[] (core keys)": {k: None for k in ("index", "name", "skipped", "mask_pixels")},
        "frames[] (image preprocessor)": result["frames"][0],
        "frames[] (paper preprocessor)": paper["frames"][0],
    }
    missing = {where: [k for k in d if not _documented(k, text)] for where, d in groups.items()}
    assert not any(missing.values()), f"docs/results.md does not name these keys: {missing}"


@pytest.mark.slow
def test_results_md_names_every_evaluation_key(small_sequence):
    registry = load_registry()
    text = (DOCS / "results.md").read_text()
    seq = open_sequences(registry, small_sequence)[0]
    ev = evaluate(registry, [seq], Config(pipeline=PipelineParams(k=3))).to_dict()
    json.dumps(ev)
    groups = {
        "evaluation": ev,
        "metrics": ev["metrics"],
        "sequences[]": ev["sequences"][0],
        "per_object": next(iter(ev["metrics"]["per_object"].values())),
        "config": ev["config"],
    }
    missing = {where: [k for k in d if not _documented(k, text)] for where, d in groups.items()}
    assert not any(missing.values()), f"docs/results.md does not name these evaluation keys: {missing}"


# -- data-formats.md --------------------------------------------------------------------------------


def test_data_formats_has_a_section_per_reader(builtin):
    text = (DOCS / "data-formats.md").read_text()
    sections = re.findall(r"^## `(\w+)`", text, flags=re.M)
    assert sections == sorted(sections) or set(sections)
    missing = set(builtin.names("reader")) - set(sections)
    assert not missing, f"docs/data-formats.md has no '## `NAME`' section for the readers {sorted(missing)}"


# -- links ------------------------------------------------------------------------------------------


def _slug(title: str) -> str:
    """GitHub's heading anchor: lower case, punctuation dropped (not - or _), spaces to dashes."""
    return re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    return {_slug(m) for m in re.findall(r"^#+ (.*)$", path.read_text(), flags=re.M)}


DOC_PAGES = sorted(DOCS.glob("*.md"))


@pytest.mark.parametrize("page", DOC_PAGES, ids=[p.name for p in DOC_PAGES])
def test_links_resolve(page):
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.M | re.S)  # not inside code blocks
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):
            continue
        file, _, anchor = target.partition("#")
        dest = (page.parent / file).resolve() if file else page
        if not dest.exists():
            bad.append(f"{target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target} (no such heading)")
    assert not bad, f"{page.name}: broken links: {bad}"


def test_index_links_every_page():
    index = (DOCS / "index.md").read_text()
    for page in DOC_PAGES:
        if page.name != "index.md":
            assert f"]({page.name})" in index, f"docs/index.md does not link {page.name}"
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        assert f"notebooks/{notebook.name}" in index, f"docs/index.md does not link {notebook.name}"


# -- the documents a newcomer reads first ---------------------------------------------------------------

README, CHANGELOG, BENCHMARKS = ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "benchmarks" / "README.md"
CHANGELOG_SECTIONS = {"Added", "Changed", "Deprecated", "Removed", "Fixed", "Security"}


def _section(text: str, title: str) -> list[str]:
    """The non-blank lines under the heading ``title`` up to the next heading of its level or above."""
    lines = text.splitlines()
    start = lines.index(title)
    level = title.split()[0]
    out = []
    for line in lines[start + 1 :]:
        if line.startswith("#") and len(line.split()[0]) <= len(level):
            break
        out.append(line)
    return [line for line in out if line.strip()]


@pytest.mark.parametrize("page", [README, CHANGELOG, BENCHMARKS], ids=lambda p: str(p.relative_to(ROOT)))
def test_top_level_links_resolve(page):
    test_links_resolve(page)


def test_readme_reads_in_five_minutes():
    text = README.read_text()
    assert len(text.splitlines()) <= 200, f"README.md has {len(text.splitlines())} lines; at most 200"
    first = text.splitlines()[:4]
    assert first[0] == "```" and first[1].startswith("make app ") and first[2].startswith("make test ")
    limits = _section(text, "## Known limitations")
    assert 0 < len(limits) <= 15, f"README's known limitations run to {len(limits)} lines; at most 15"
    assert all("docs/limitations.md#" in item for item in "\n".join(limits).split("\n- ")), (
        "every known limitation links to its measured detail in docs/limitations.md"
    )


def test_changelog_is_releases_of_short_entries():
    text = CHANGELOG.read_text()
    lines = text.splitlines()
    assert len(lines) <= 400, f"CHANGELOG.md has {len(lines)} lines; at most 400"
    releases = [line for line in lines if line.startswith("## ")]
    assert releases and all(re.match(r"## \[(Unreleased|\d+\.\d+\.\d+)\]", r) for r in releases), releases
    kinds = {line[4:] for line in lines if line.startswith("### ")}
    assert kinds <= CHANGELOG_SECTIONS, (
        f"sections other than Keep a Changelog's: {kinds - CHANGELOG_SECTIONS}"
    )
    assert not [line for line in lines if line.startswith("#### ")], "no sub-sections under a kind of change"
    entries = re.split(r"^- ", text, flags=re.M)[1:]
    long = [e.splitlines()[0] for e in entries if len(e.split("\n\n")[0].strip().splitlines()) > 3]
    assert not long, f"entries longer than three lines: {long}"


def test_benchmarks_readme_opens_with_its_tables():
    text = BENCHMARKS.read_text()
    body = text.split("## Current results", 1)[1].split("\n## ", 1)[0]
    for table in re.split(r"^### ", body, flags=re.M)[1:]:
        title = table.splitlines()[0]
        assert "Remake" in table.split("|", 1)[0], f"table {title!r}: the command that remakes it comes first"
        prose = [p for p in table.split("\n\n") if p.strip() and not p.lstrip().startswith(("|", "Remake"))]
        assert len(prose) <= 2, f"table {title!r}: at most a paragraph of prose, got {len(prose) - 1}"
