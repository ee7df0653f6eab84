"""Every notebook runs top to bottom at small size (MI_SHADOWMAP_SMALL=1).

The kernel is this interpreter: a kernelspec naming ``sys.executable`` is
written to a temporary JUPYTER_PATH (which Jupyter searches first), so the
notebooks import the same ``mi_shadowmap`` as the tests, in /work/venv or in
CI's fresh ``.venv`` alike. The first executed cell checks that.
"""
import json
import re
import sys

import pytest

from conftest import ROOT

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
ALLOWED_IMPORTS = {"os", "mi_shadowmap", "matplotlib", "numpy"}
KERNEL = "mi-shadowmap-test"


@pytest.fixture(scope="module")
def kernel_env(tmp_path_factory):
    """A kernelspec running this interpreter, found first through JUPYTER_PATH."""
    root = tmp_path_factory.mktemp("jupyter")
    spec_dir = root / "kernels" / KERNEL
    spec_dir.mkdir(parents=True)
    (spec_dir / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "mi_shadowmap tests", "language": "python"}))
    return root


def test_there_are_notebooks():
    assert {p.stem for p in NOTEBOOKS} >= {"01_quickstart", "05_speed_accuracy"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_committed_clean(path):
    """No outputs, no execution counts, and only the allowed imports."""
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    assert nb.cells[0].cell_type == "markdown" and "Overview" in nb.cells[0].source
    assert "What you will learn" in nb.cells[0].source
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        assert cell.outputs == [] and cell.execution_count is None, "commit without outputs"
        for mod in re.findall(r"^\s*(?:from|import)\s+([A-Za-z_][\w]*)", cell.source, re.M):
            assert mod in ALLOWED_IMPORTS, f"{path.name} imports {mod}"
    assert "MI_SHADOWMAP_SMALL" in nb.cells[1].source + "".join(
        c.source for c in nb.cells if c.cell_type == "code")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, kernel_env, monkeypatch, tmp_path):
    monkeypatch.setenv("JUPYTER_PATH", str(kernel_env))
    monkeypatch.setenv("MI_SHADOWMAP_SMALL", "1")
    nb = nbformat.read(path, as_version=4)
    check = nbformat.v4.new_code_cell(
        "import sys, os\n"
        f"assert sys.executable == {sys.executable!r}, sys.executable\n"
        "assert os.environ['MI_SHADOWMAP_SMALL'] == '1'")
    nb.cells.insert(0, check)
    client = nbclient.NotebookClient(nb, kernel_name=KERNEL, timeout=600,
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs
              if o.output_type == "error"]
    assert not errors
