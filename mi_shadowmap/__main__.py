"""``python -m mi_shadowmap ...``: the ``mi-shadowmap`` command line
(:func:`mi_shadowmap.cli.main`), for an environment whose scripts folder is not on
``PATH``."""
import sys

from .cli import main

sys.exit(main())
