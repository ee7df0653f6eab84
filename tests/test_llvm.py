"""LLVM discovery: version parsing, search order and the error when nothing works."""
import os
import subprocess
import sys

import pytest

from mi_shadowmap import _llvm


@pytest.mark.parametrize("path, version", [
    ("/venv/lib/libLLVM.so.23.1", 23),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1", 14),
    ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
    ("/usr/lib/libfoo.so", None),
])
def test_version_from_name(path, version):
    assert _llvm.llvm_version_from_name(path) == version


def test_configured_library_is_recent():
    path = os.environ[_llvm.ENV_VAR]
    assert os.path.isfile(path)
    assert (_llvm.llvm_version_from_name(path) or 99) >= _llvm.MIN_LLVM_VERSION


def test_old_llvm_is_skipped_and_error_says_how_to_fix(monkeypatch):
    old = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"
    monkeypatch.setattr(_llvm, "_candidates", lambda: [old])
    with pytest.raises(_llvm.LLVMNotFoundError) as e:
        _llvm.find_libllvm()
    msg = str(e.value)
    assert old in msg and "LLVM 15" in msg
    assert "pip install karellen-llvm-core" in msg and _llvm.ENV_VAR in msg


def test_pip_llvm_preferred_over_system(monkeypatch):
    cands = ["/venv/lib/libLLVM.so.23.1", "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"]
    monkeypatch.setattr(_llvm, "_candidates", lambda: cands)
    assert _llvm.find_libllvm()[0] == cands[0]


def test_user_setting_is_respected_and_checked(monkeypatch, tmp_path):
    fake = tmp_path / "libLLVM-18.so"
    fake.write_bytes(b"")
    monkeypatch.setenv(_llvm.ENV_VAR, str(fake))
    assert _llvm.configure_llvm() == str(fake)
    monkeypatch.setenv(_llvm.ENV_VAR, str(tmp_path / "missing.so"))
    with pytest.raises(_llvm.LLVMNotFoundError, match="does not exist"):
        _llvm.configure_llvm()


def _run(code, env_extra=None):
    env = {k: v for k, v in os.environ.items() if k != _llvm.ENV_VAR}
    env.update(env_extra or {})
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=300)


def test_fresh_process_uses_a_recent_llvm():
    r = _run("import mi_shadowmap, drjit as dr; print(dr.detail.llvm_version()[0])")
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) >= _llvm.MIN_LLVM_VERSION


def test_importing_drjit_first_is_explained_not_crashed():
    """Dr.Jit reads DRJIT_LIBLLVM_PATH at import; importing it first cannot be fixed later."""
    r = _run("import drjit, mi_shadowmap")
    loaded_old = r.returncode != 0
    if not loaded_old:
        pytest.skip("this machine's default libLLVM is recent enough; nothing to explain")
    assert "imported before mi_shadowmap" in r.stderr
    assert _llvm.ENV_VAR in r.stderr
