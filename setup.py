"""Packaging glue pyproject.toml cannot express: ship the top-level conf/ as ``cicfw.conf``."""
from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["cicfw", "cicfw.*"]) + ["cicfw.conf"],
    package_dir={"cicfw.conf": "conf"},
)
