"""Build script: the configuration is declarative, in setup.cfg."""

from setuptools import setup

setup()
