"""The part of the build that pyproject.toml cannot say: the built-in scenes (``scenes/``, with their
textures) and their committed references (``references/``) live at the top of the source tree, and a
wheel carries them as package data, ``shadowlab/builtin_scenes`` and ``shadowlab/builtin_references``,
where ``shadowlab.scene.spec.builtin_dir`` and ``shadowlab.reference.location.builtin_references``
find them in an installed package (a source checkout reads ``scenes/`` and ``references/`` themselves).
"""

from setuptools import find_packages, setup

#: package name in the wheel -> folder of the source tree
DATA_DIRS = {"shadowlab.builtin_scenes": "scenes", "shadowlab.builtin_references": "references"}

setup(
    packages=find_packages(include=["shadowlab", "shadowlab.*"]) + list(DATA_DIRS),
    package_dir=DATA_DIRS,
    package_data={
        "shadowlab.techniques": ["engine_pages/*.html", "engine_pages/*.js"],
        "shadowlab.builtin_scenes": ["*.toml", "textures/*"],
        "shadowlab.builtin_references": ["*.toml", "*/*/truth.exr", "*/*/meta.json"],
    },
)
