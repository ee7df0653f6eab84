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


def _claims_02(out: str) -> list:
    """Figure 9 (Reeves' constant bias against the paper's single receiver depth): no
    bias is acne that the paper's smallest bias removes, and false lit grows with the
    bias (with the receiver plane left on, the four biases rendered the same)."""
    rows = {m.group(1): (float(m.group(2)), float(m.group(3))) for m in re.finditer(
        r"bias \(([^)]*)\): false shadow ([\d.]+)%, false lit ([\d.]+)%", out)}
    if set(rows) != {"0, 0", "0.2, 0.3", "0.3, 0.4", "1, 1.5"}:
        return [f"Figure 9 printed the biases {sorted(rows)}"]
    problems = []
    if not rows["0, 0"][0] > 2 * rows["0.2, 0.3"][0]:
        problems.append(f"no acne without bias: {rows}")
    if not rows["1, 1.5"][1] > rows["0, 0"][1]:
        problems.append(f"false lit does not grow with the bias: {rows}")
    return problems


def _claims_03(out: str) -> list:
    """Step 4 and the summary: PCF(k, n) of mdsm gives at most n k + 1 levels, and
    PCF(9, 2) and PCF(9, 3) as many as PCF(16, 1); without virtual samples
    second_depth's ground darkens (the visibility RMSE more than doubles)."""
    levels = {(int(k), int(n)): int(lv) for k, n, lv in
              re.findall(r"PCF\((\d+), (\d+)\):\s+(\d+) levels", out)}
    if len(levels) != 4:
        return [f"Step 4 printed {levels}"]
    problems = [f"PCF({k}, {n}): {lv} levels > n k + 1" for (k, n), lv in levels.items()
                if lv > n * k + 1]
    if min(levels[(9, 2)], levels[(9, 3)]) < levels[(16, 1)]:
        problems.append(f"PCF(9, 2), PCF(9, 3) fewer levels than PCF(16, 1): {levels}")
    rmse = dict(re.findall(r"^(second_depth.*?)\s+false shadow.*vis RMSE ([\d.]+)", out, re.M))
    with_vs, without = rmse.get("second_depth"), rmse.get("second_depth, no virtual samples")
    if with_vs is None or without is None or not float(without) > 2 * float(with_vs):
        problems.append(f"second_depth without virtual samples: {rmse}")
    return problems


def _claims_08(out: str) -> list:
    """Step 2: without antialiased silhouettes vsm's gradient at the start is orders of
    magnitude smaller (the text says about 650x at full size, 0 when small)."""
    g = dict(re.findall(r"gradient at the start, (.+?)\s+\[.*\], \|g\| (\S+)", out))
    aa, plain = g.get("vsm"), g.get("vsm, antialias='never'")
    if aa is None or plain is None:
        return [f"Step 2 printed {g}"]
    return [] if float(plain) < 0.01 * float(aa) else [f"|g| without antialiasing: {g}"]


#: What a notebook's text claims about its printed numbers, checked on the small run:
#: ``{stem: fn(printed text) -> problems}``.
CLAIMS = {"02_pcf_parameters": _claims_02, "03_bias_and_second_depth": _claims_03,
          "08_differentiable_shadows": _claims_08}


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
    printed = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                      for o in c.outputs if o.output_type == "stream")
    problems = CLAIMS.get(path.stem, lambda out: [])(printed)
    assert not problems, f"{path.name}: its text does not hold:\n  " + "\n  ".join(problems)
