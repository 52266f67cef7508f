"""Package layout that pyproject.toml alone cannot say: the repository's ``profiles/`` folder (the
shipped robot profiles and their URDFs, which README's commands name as ``profiles/so101.yaml``) is
installed as ``crtk_bridge/profiles``, so an installed package finds them wherever it runs
(``crtk_bridge.profile.shipped_profiles_dir``). Everything else is in pyproject.toml."""

from setuptools import find_packages, setup

setup(
    packages=[*find_packages(include=["crtk_bridge*"]), "crtk_bridge.profiles"],
    package_dir={"crtk_bridge.profiles": "profiles"},
    package_data={"crtk_bridge.profiles": ["*.yaml", "urdf/*.urdf", "urdf/meshes/*"]},
)
