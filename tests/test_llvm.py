"""LLVM discovery: version parsing, search order, the start-up hook and the errors."""
import os
import site
import subprocess
import sys
import sysconfig

import pytest

import _mi_shadowmap_llvm as startup
from mi_shadowmap import _llvm

OLD_SYSTEM_LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"


@pytest.mark.parametrize("path, version", [
    ("/venv/lib/libLLVM.so.23.1", 23),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1", 14),
    ("/usr/lib/llvm-17/lib/libLLVM.so", 17),
    ("/opt/homebrew/lib/libLLVM.18.dylib", 18),
    ("/venv/lib/libLLVM.so", None),
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


def _fake_prefix(tmp_path, monkeypatch, names):
    lib = tmp_path / "lib"
    lib.mkdir()
    for name in names:
        (lib / name).write_bytes(b"")
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    monkeypatch.setattr(sys, "base_prefix", str(tmp_path))
    monkeypatch.setattr(site, "ENABLE_USER_SITE", False)
    monkeypatch.delenv(_llvm.ENV_VAR, raising=False)
    return lib


def test_startup_hook_sets_newest_environment_llvm(tmp_path, monkeypatch):
    lib = _fake_prefix(tmp_path, monkeypatch,
                       ["libLLVM-15.so.1", "libLLVM.so.17.0", "libLLVM.so.23.1", "libLTO.so.23.1"])
    assert startup.set_default_libllvm() == str(lib / "libLLVM.so.23.1")
    assert os.environ[_llvm.ENV_VAR] == str(lib / "libLLVM.so.23.1")


def test_startup_hook_finds_a_user_install(tmp_path, monkeypatch):
    """``pip install --user`` (no venv, no root) puts karellen-llvm-core's libLLVM into
    ~/.local/lib: the hook and the search looked only in sys.prefix/base_prefix, and
    ``import mi_shadowmap`` said no usable libLLVM was found."""
    (tmp_path / "env").mkdir()
    _fake_prefix(tmp_path / "env", monkeypatch, ["libLLVM-15.so.1"])
    user_lib = tmp_path / "user" / "lib"
    user_lib.mkdir(parents=True)
    (user_lib / "libLLVM.so.23.1").write_bytes(b"")
    monkeypatch.setattr(site, "USER_BASE", str(tmp_path / "user"))
    monkeypatch.setattr(site, "ENABLE_USER_SITE", True)
    assert startup.set_default_libllvm() == str(user_lib / "libLLVM.so.23.1")
    monkeypatch.delenv(_llvm.ENV_VAR)
    assert _llvm.find_libllvm()[0] == str(user_lib / "libLLVM.so.23.1")
    monkeypatch.setattr(site, "ENABLE_USER_SITE", False)   # a venv: user site disabled
    assert startup.set_default_libllvm() is None


def test_search_finds_the_llvm_beside_a_site_packages_on_sys_path(tmp_path, monkeypatch):
    """Under ``python -S`` sys.prefix is not the venv's: with the venv's site-packages put
    on sys.path by hand, ``import mi_shadowmap`` first found no libLLVM beside it."""
    (tmp_path / "base").mkdir()
    _fake_prefix(tmp_path / "base", monkeypatch, [])
    venv_lib = tmp_path / "venv" / "lib"
    (venv_lib / "python3.11" / "site-packages").mkdir(parents=True)
    (venv_lib / "libLLVM.so.23.1").write_bytes(b"")
    monkeypatch.setattr(sys, "path", [str(venv_lib / "python3.11" / "site-packages")])
    monkeypatch.delenv("VIRTUAL_ENV", raising=False)
    assert _llvm.find_libllvm()[0] == str(venv_lib / "libLLVM.so.23.1")


def test_startup_hook_skips_old_and_unversioned_libraries(tmp_path, monkeypatch):
    _fake_prefix(tmp_path, monkeypatch, ["libLLVM-14.so", "libLLVM-15.so.1", "libLLVM.so"])
    assert startup.set_default_libllvm() is None
    assert _llvm.ENV_VAR not in os.environ


def test_startup_hook_leaves_user_setting_untouched(tmp_path, monkeypatch):
    _fake_prefix(tmp_path, monkeypatch, ["libLLVM.so.23.1"])
    monkeypatch.setenv(_llvm.ENV_VAR, "/my/own/libLLVM-15.so")   # even old or missing
    assert startup.set_default_libllvm() is None
    assert os.environ[_llvm.ENV_VAR] == "/my/own/libLLVM-15.so"


def test_startup_hook_never_raises(monkeypatch):
    monkeypatch.delenv(_llvm.ENV_VAR, raising=False)

    def boom():
        raise OSError("unreadable")
    monkeypatch.setattr(startup, "prefix_libraries", boom)
    assert startup.set_default_libllvm() is None
    assert _llvm.ENV_VAR not in os.environ


def test_pth_is_installed_in_site_packages():
    pth = os.path.join(sysconfig.get_paths()["purelib"], "mi_shadowmap_llvm.pth")
    assert os.path.isfile(pth), "reinstall the package: pip install -e ."
    line = open(pth, encoding="utf-8").read()
    assert line.startswith("import ") and line.count("\n") == 1
    assert "mi_shadowmap." not in line and "mitsuba" not in line and "drjit" not in line


RENDER_TINY_CBOX = """
import drjit as dr
scene = mi.cornell_box()
scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = 16
img = mi.render(mi.load_dict(scene), integrator=mi.load_dict({"type": "shadowmap"}), spp=1)
assert img.shape[:2] == (16, 16) and dr.all(dr.isfinite(img), axis=None), img
print(dr.detail.llvm_version()[0])
"""


def test_mitsuba_imported_first_renders_with_a_recent_llvm():
    r = _run("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mi_shadowmap"
             + RENDER_TINY_CBOX)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) >= _llvm.MIN_LLVM_VERSION


def test_drjit_imported_first_works():
    r = _run("import drjit, mi_shadowmap; import mitsuba as mi" + RENDER_TINY_CBOX)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) >= _llvm.MIN_LLVM_VERSION


def test_user_forced_old_llvm_is_explained_not_crashed():
    """A DRJIT_LIBLLVM_PATH set by the user is respected; an old one is refused clearly."""
    if not os.path.isfile(OLD_SYSTEM_LLVM):
        pytest.skip(f"needs an old system libLLVM at {OLD_SYSTEM_LLVM}")
    r = _run("import drjit, mi_shadowmap", {_llvm.ENV_VAR: OLD_SYSTEM_LLVM})
    assert r.returncode != 0
    assert "LLVMNotFoundError" in r.stderr and "LLVM 15" in r.stderr
    assert f"{_llvm.ENV_VAR}={OLD_SYSTEM_LLVM} was set outside mi_shadowmap" in r.stderr


def test_drjit_first_without_startup_hook_is_explained():
    """Under ``python -S`` no .pth runs: importing drjit first cannot be fixed later."""
    paths = [sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"],
             os.path.dirname(os.path.dirname(_llvm.__file__)),
             os.path.dirname(startup.__file__)]
    env = {k: v for k, v in os.environ.items() if k != _llvm.ENV_VAR}
    env["VIRTUAL_ENV"] = sys.prefix   # -S also skips the venv's sys.prefix; let the search see it
    code = f"import sys; sys.path[:0] = {paths!r}; import drjit, mi_shadowmap"
    r = subprocess.run([sys.executable, "-S", "-c", code], capture_output=True, text=True,
                       env=env, timeout=300)
    if r.returncode == 0:
        pytest.skip("Dr.Jit's own choice of libLLVM is recent enough here; nothing to explain")
    assert "imported before mi_shadowmap" in r.stderr and "did not run" in r.stderr
    assert _llvm.ENV_VAR in r.stderr


OLDER_SYSTEM_LLVM = "/usr/lib/x86_64-linux-gnu/libLLVM-14.so.1"


def test_llvm_refused_by_drjit_is_named_not_reported_as_version_minus_one():
    """Dr.Jit 1.5 refuses LLVM 14 outright (backend inactive, llvm_version() == (-1, -1, -1)):
    the error said "Dr.Jit loaded LLVM -1.-1.-1, which crashes it"."""
    if not os.path.isfile(OLDER_SYSTEM_LLVM):
        pytest.skip(f"needs an old system libLLVM at {OLDER_SYSTEM_LLVM}")
    r = _run("import mi_shadowmap", {_llvm.ENV_VAR: OLDER_SYSTEM_LLVM})
    assert r.returncode != 0
    assert "LLVMNotFoundError" in r.stderr and "-1.-1.-1" not in r.stderr
    assert "inactive" in r.stderr and "LLVM 14" in r.stderr
    assert f"{_llvm.ENV_VAR}={OLDER_SYSTEM_LLVM} was set outside mi_shadowmap" in r.stderr


def test_user_setting_to_a_bare_library_name_is_left_to_the_loader():
    """``DRJIT_LIBLLVM_PATH=libLLVM.so.23.1`` with its folder in LD_LIBRARY_PATH: Dr.Jit
    loads it (dlopen searches the loader's paths), but mi_shadowmap said it "does not
    exist" (it looked for the name in the current folder)."""
    path = os.environ[_llvm.ENV_VAR]
    r = _run("import mi_shadowmap, drjit as dr; print(dr.detail.llvm_version()[0])",
             {_llvm.ENV_VAR: os.path.basename(path),
              "LD_LIBRARY_PATH": os.path.dirname(path)})
    assert r.returncode == 0, r.stderr
    assert int(r.stdout.split()[-1]) >= _llvm.MIN_LLVM_VERSION


def test_user_setting_to_a_directory_says_so(monkeypatch, tmp_path):
    monkeypatch.setenv(_llvm.ENV_VAR, str(tmp_path))
    with pytest.raises(_llvm.LLVMNotFoundError, match="is a directory, not a library file"):
        _llvm.configure_llvm()


@pytest.mark.parametrize("how", ["module", "script"])
def test_command_line_reports_an_unusable_llvm_without_a_traceback(how, tmp_path):
    """``mi-shadowmap`` and ``python -m mi_shadowmap`` with no usable LLVM: the import of the
    package raised before the command line's own error handling, so the user got a
    traceback; now one error line and exit status 2 (``--debug`` keeps the traceback)."""
    missing = str(tmp_path / "libLLVM-18.so")
    env = {k: v for k, v in os.environ.items() if k != _llvm.ENV_VAR}
    env[_llvm.ENV_VAR] = missing
    script = os.path.join(os.path.dirname(sys.executable), "mi-shadowmap")
    if how == "script" and not os.path.isfile(script):
        pytest.skip("the mi-shadowmap script is not installed beside this interpreter")
    cmd = [sys.executable, "-m", "mi_shadowmap"] if how == "module" else [script]
    r = subprocess.run(cmd + ["compare"], capture_output=True, text=True, env=env,
                       timeout=300, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert r.stderr.startswith("mi-shadowmap: error: ") and "does not exist" in r.stderr
    assert missing in r.stderr
    r = subprocess.run(cmd + ["--debug", "compare"], capture_output=True, text=True, env=env,
                       timeout=300, cwd=tmp_path)
    assert r.returncode != 0 and "Traceback" in r.stderr and "LLVMNotFoundError" in r.stderr
    r = subprocess.run([sys.executable, "-c", "import mi_shadowmap"], capture_output=True,
                       text=True, env=env, timeout=300, cwd=tmp_path)
    assert r.returncode != 0 and "LLVMNotFoundError" in r.stderr   # from Python: raises


def test_a_program_run_with_dash_m_that_imports_the_package_gets_the_exception(tmp_path):
    """Only the package's own command line turns an unusable LLVM into one error line
    and exit status 2: ``python -m yourpkg``, whose package imports ``mi_shadowmap``,
    imports it from Python and gets :class:`LLVMNotFoundError` (it got the command
    line's ``mi-shadowmap: error:`` line and ``SystemExit(2)``: ``sys.argv[0]`` is
    ``"-m"`` while runpy imports any package run with ``-m``)."""
    pkg = tmp_path / "yourpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("import mi_shadowmap\n")
    (pkg / "__main__.py").write_text("print('ran')\n")
    env = {k: v for k, v in os.environ.items() if k != _llvm.ENV_VAR}
    env[_llvm.ENV_VAR] = str(tmp_path / "libLLVM-18.so")
    # the mi_shadowmap these tests import, beside the program
    here = os.path.dirname(os.path.dirname(os.path.abspath(_llvm.__file__)))
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), here])
    r = subprocess.run([sys.executable, "-m", "yourpkg"], capture_output=True, text=True,
                       env=env, timeout=300, cwd=tmp_path)
    assert r.returncode == 1 and "LLVMNotFoundError" in r.stderr, r.stderr
    assert "mi-shadowmap: error:" not in r.stderr
    for cmd in (["-m", "mi_shadowmap"], ["-mmi_shadowmap"], ["-Bm", "mi_shadowmap"]):
        r = subprocess.run([sys.executable, *cmd, "compare"], capture_output=True,
                           text=True, env=env, timeout=300, cwd=tmp_path)
        assert r.returncode == 2 and r.stderr.startswith("mi-shadowmap: error: "), (cmd, r.stderr)

