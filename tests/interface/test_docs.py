"""The docs site's sources hold together (make docs builds them; this reads them, in a second).

The front page's toctrees reach the API reference and the demo pages, every literate demo is
a jupytext percent script, every page the README links to exists, and the README stays a
front page whose Python example uses only the contract's names.
"""

import re

from conftest import ROOT

DOCS = ROOT / "docs"
README = (ROOT / "README.md").read_text()


def toctree_entries() -> list[str]:
    """Document names in the toctrees of docs/index.md ("Title <name>" entries give the name)."""
    blocks = re.findall(r"```\{toctree\}\n(.*?)```", (DOCS / "index.md").read_text(), re.S)
    entries = []
    for line in "\n".join(blocks).splitlines():
        line = line.strip()
        if line and not line.startswith(":"):
            named = re.search(r"<(.+)>$", line)
            entries.append(named.group(1) if named else line)
    return entries


def literate_demos() -> list[str]:
    return re.findall(r'"(\w+\.py)"', re.search(r"LITERATE_DEMOS = \[(.*?)\]", (DOCS / "conf.py").read_text()).group(1))


def test_toctree_holds_the_api_reference_and_the_demo_pages():
    entries = toctree_entries()
    assert "api" in entries
    demos = literate_demos()
    assert "letter_a_poisson.py" in demos
    for script in demos:
        assert f"demos/{script.removesuffix('.py')}" in entries, script


def test_every_toctree_entry_has_its_page():
    for entry in toctree_entries():
        if entry.startswith("demos/"):  # written from demos/*.py by conf.py at build time
            assert (ROOT / f"{entry}.py").exists(), entry
        else:
            assert (DOCS / f"{entry}.md").exists(), entry


def test_the_api_reference_documents_the_package():
    api = (DOCS / "api.md").read_text()
    assert re.search(r"^\.\. automodule:: fenics_elasto$\n\s+:members:", api, re.M)
    for module in ("fenics_elasto.inverse.estimator", "fenics_elasto.model.scene"):
        assert f".. automodule:: {module}\n" in api


def test_literate_demos_are_percent_scripts_that_open_with_prose():
    for script in literate_demos():
        text = (ROOT / "demos" / script).read_text()
        assert text.startswith("# %% [markdown]\n# # "), script  # a title first, as DOLFINx's demos
        assert text.count("# %%\n") >= 3, script  # code cells between the prose


def test_every_page_the_readme_links_to_exists():
    links = [target for target in re.findall(r"\]\(([^)\s]+)\)", README) if "://" not in target]
    assert len(links) >= 10
    for target in links:
        assert (ROOT / target.split("#")[0]).exists(), target


def test_readme_is_a_front_page():
    assert len(README.splitlines()) <= 250
    assert "make demo" in README and "make test" in README
    python = re.search(r"```python\n(.*?)```", README, re.S).group(1)
    assert 10 <= len(python.splitlines()) <= 15
    assert set(re.findall(r"\bfe\.(\w+)", python)) <= CONTRACT_NAMES


# The names of interface.md's "Python API", which outside checks script against.
CONTRACT_NAMES = {"__version__", "build_scene", "load_scene", "Scene", "simulate", "Target", "estimate",
                  "train", "Bases", "render", "UserError"}
