"""Packages of the distribution (metadata and package data: pyproject.toml).

The presets in `configs/` stay at the top of the source tree, where users and the docs find them,
and are installed as the package `c4d_configs` (`c4d_core.config` finds them with importlib.resources),
so every install (wheel, sdist, editable) carries them. pyproject.toml alone cannot map a folder
onto another package name next to automatic package discovery, hence this file.
"""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["c4d_core*", "datagen*", "dynpt*", "c4d_pipeline*", "c4d*"]), "c4d_configs"],
    package_dir={"c4d_configs": "configs"},
)
