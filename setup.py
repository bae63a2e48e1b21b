"""Build hook: ship the repository's schemas/ and scenarios/ inside the wheel.

They stay at the top of the repository (where users and docker-compose look for them); a
non-editable install gets a copy under ``diffpos_services/_data`` that
:mod:`diffpos_services.resources` finds. Everything else is in pyproject.toml.
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

DATA_DIRS = {"schemas": "*.json", "scenarios": "*.toml"}


class BuildPyWithData(build_py):
    def run(self):
        super().run()
        here = Path(__file__).resolve().parent
        for name, pattern in DATA_DIRS.items():
            dst = Path(self.build_lib, "diffpos_services", "_data", name)
            dst.mkdir(parents=True, exist_ok=True)
            for f in sorted((here / name).glob(pattern)):
                shutil.copy2(f, dst / f.name)


setup(cmdclass={"build_py": BuildPyWithData})
