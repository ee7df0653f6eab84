"""Build hook: install ``mi_shadowmap_llvm.pth`` at the root of site-packages.

Its single line runs ``_mi_shadowmap_llvm.set_default_libllvm()`` at every
interpreter start, so that ``DRJIT_LIBLLVM_PATH`` points at the environment's
libLLVM >= 16 before anything imports ``drjit`` (see ``_mi_shadowmap_llvm.py``).
All other metadata is in pyproject.toml.
"""
import os

from setuptools import setup
from setuptools.command.build_py import build_py

PTH_NAME = "mi_shadowmap_llvm.pth"
# One line, must start with "import" (site.py executes such lines). The try/except
# keeps interpreter start silent even if the module cannot be imported.
PTH_LINE = ('import os; exec("try:\\n from _mi_shadowmap_llvm import set_default_libllvm\\n'
            ' set_default_libllvm()\\nexcept Exception:\\n pass")\n')


class build_py_with_pth(build_py):
    """build_py that also writes the .pth where it ends up at the wheel's root.

    * Regular wheel (``pip install .``): the content of ``build_lib`` is the
      wheel's root, i.e. site-packages.
    * Editable wheel (``pip install -e .``, PEP 660): setuptools' editable_wheel
      does not put ``build_lib`` into the wheel; it packs the ``install``
      command's ``install_lib`` folder (the unpacked wheel) instead, so the file
      goes there (setuptools >= 64).
    """

    def _pth_dir(self):
        if self.editable_mode:
            return getattr(self.get_finalized_command("install"), "install_lib", None)
        return self.build_lib

    def run(self):
        super().run()
        folder = self._pth_dir()
        if folder:
            os.makedirs(folder, exist_ok=True)
            with open(os.path.join(folder, PTH_NAME), "w", encoding="utf-8") as f:
                f.write(PTH_LINE)

    def get_outputs(self, include_bytecode=True):
        outputs = super().get_outputs(include_bytecode)
        if not self.editable_mode:
            outputs.append(os.path.join(self.build_lib, PTH_NAME))
        return outputs


setup(cmdclass={"build_py": build_py_with_pth})
