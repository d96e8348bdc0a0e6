"""The documentation: a short README, references that match the code, links that resolve."""
import re

from tests.helpers import REPO, load_script


def _reference_docs():
    return load_script("scripts/reference_docs.py", "reference_docs")


def test_the_readme_is_a_front_door():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 250
    commands = re.findall(r"```bash\n(.*?)```", text.split("## The two commands")[1].split("\n## ")[0], re.S)
    assert [c.strip() for c in commands] == [
        "python3 -m venv .venv && . .venv/bin/activate && pip install . && mpe3d reproduce-paper --scale quick",
        "pip install '.[test]' && python -m pytest"]
    assert "pip install '.[test]' && python -m pytest" in (REPO / ".ci" / "run").read_text()


def test_the_reference_pages_are_generated_from_the_current_code():
    pages = _reference_docs().pages()
    for name, text in pages.items():
        path = REPO / "docs" / "reference" / name
        assert path.read_text() == text, f"{path} is stale: python scripts/reference_docs.py"


def test_a_config_key_added_without_its_page_is_caught(monkeypatch):
    from mpe3d.harness.experiment import config

    reference = _reference_docs()
    committed = (REPO / "docs" / "reference" / "config.md").read_text()
    monkeypatch.setitem(config.KEYS, "noise.new_knob", config.Key(1.0, float, "a key nobody documented"))
    assert reference.pages()["config.md"] != committed
    assert "`noise.new_knob`" in reference.pages()["config.md"]


def test_every_relative_link_resolves():
    pages = [REPO / "README.md", *(REPO / "docs").rglob("*.md")]
    broken = []
    for page in pages:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            if not (page.parent / target).exists():
                broken.append(f"{page.relative_to(REPO)} -> {target}")
    assert not broken, broken


def test_the_architecture_page_shows_the_enforced_layers_in_their_order():
    """The rule lives in pyproject.toml's contracts; the page's diagram is its picture."""
    from tests.helpers import pyproject

    contracts = pyproject()["tool"]["importlinter"]["contracts"]
    layers = next(c for c in contracts if c["type"] == "layers" and "containers" not in c)["layers"]
    page = (REPO / "docs" / "architecture.md").read_text()
    diagram = page.split("## The layer rule")[1].split("```")[1]
    drawn = [line.split("  ")[0].strip() for line in diagram.strip().splitlines()]
    assert drawn == [layer.replace("mpe3d.", "") for layer in layers]
