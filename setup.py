"""Package discovery that pyproject.toml cannot express: ``nodes/`` installs as ``flowrt.nodes``.

Everything else (metadata, dependencies, entry points, package data) is in pyproject.toml.
"""

from setuptools import find_packages, setup

nodes = ["flowrt.nodes", *(f"flowrt.nodes.{p}" for p in find_packages("nodes"))]
setup(
    packages=[*find_packages(include=["flowrt", "flowrt.*"]), *nodes],
    package_dir={"flowrt.nodes": "nodes"},
)
