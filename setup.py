"""Build hook: the repository's top-level ``conf/`` ships inside the wheel as ``rlexp/conf``.

Everything else is declared in pyproject.toml. ``conf/`` stays at the top of the repository (the
layout the README promises); an editable install reads it there (``rlexp.config.paths.CONF_DIR``), a wheel
or an sdist-built wheel carries a copy under the package, found with ``importlib.resources``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

CONF = Path(__file__).resolve().parent / "conf"


class build_py_with_conf(build_py):  # noqa: N801 (setuptools command naming)
    """``build_py`` plus ``conf/**/*.yaml`` copied to ``<build_lib>/rlexp/conf``."""

    def run(self) -> None:
        super().run()
        if self.editable_mode:  # the checkout's conf/ is read in place
            return
        if not (CONF / "config.yaml").is_file():
            raise FileNotFoundError(f"{CONF}/config.yaml is missing: rlexp's configs must ship")
        target = Path(self.build_lib) / "rlexp" / "conf"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(CONF, target, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        target = Path(self.build_lib) / "rlexp" / "conf"
        conf = [str(target / p.relative_to(CONF)) for p in CONF.rglob("*.yaml")]
        return [*super().get_outputs(include_bytecode), *conf]


setup(cmdclass={"build_py": build_py_with_conf})
