"""Package layout that pyproject.toml alone cannot say: the repository's ``profiles/`` folder (the
shipped robot profiles and their URDFs, which README's commands name as ``profiles/so101.yaml``) is
installed as ``crtk_bridge/profiles``, so an installed package finds them wherever it runs
(``crtk_bridge.profile.shipped_profiles_dir``); and the client library, ``crtk_client``, whose
source is the ``crtk-client`` distribution's (``clients/python``, installable alone), is installed
with crtk-bridge. Everything else is in pyproject.toml."""

from setuptools import find_packages, setup

CLIENT = "clients/python"

setup(
    packages=[*find_packages(include=["crtk_bridge*"]), "crtk_bridge.profiles",
              *find_packages(CLIENT, include=["crtk_client*"])],
    package_dir={"crtk_bridge.profiles": "profiles", "crtk_client": f"{CLIENT}/crtk_client"},
    package_data={"crtk_bridge.profiles": ["*.yaml", "urdf/*.urdf", "urdf/meshes/*"]},
)
