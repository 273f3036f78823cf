"""Package discovery that pyproject.toml cannot express: ``nodes/`` installs as ``flowrt.nodes``,
``graphs/`` as ``flowrt.examples`` (the example graphs a wheel's user copies out with
``flowrt examples --copy .``).

Everything else (metadata, dependencies, entry points, package data) is in pyproject.toml.
"""

from setuptools import find_packages, setup

nodes = ["flowrt.nodes", *(f"flowrt.nodes.{p}" for p in find_packages("nodes"))]
setup(
    packages=[*find_packages(include=["flowrt", "flowrt.*"]), *nodes, "flowrt.examples"],
    package_dir={"flowrt.nodes": "nodes", "flowrt.examples": "graphs"},
)
