"""Build hook: generate the gRPC stubs from proto/ before the packages are collected."""

import importlib.util
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithStubs(build_py):
    def run(self) -> None:
        spec = importlib.util.spec_from_file_location(
            "generate", Path(__file__).parent / "proto" / "generate.py"
        )
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        module.generate()
        super().run()


setup(cmdclass={"build_py": BuildPyWithStubs})
