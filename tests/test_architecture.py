"""docs/architecture.md is the design of record, in the repository: the import graph of the code is
the one its Dependencies table says (every import, lazy ones too), and no product file cites a
design document outside the repository (DESIGN.md, ../shared/...)."""

from __future__ import annotations

import ast
import fnmatch
import re

from .conftest import ROOT

PACKAGE = ROOT / "crtk_bridge"
#: the client distribution's package (clients/python), checked with the same table
CLIENT = ROOT / "clients" / "python" / "crtk_client"
#: import package -> its folder's repository path
PACKAGES = {"crtk_bridge": "crtk_bridge", "crtk_client": "clients/python/crtk_client"}
ARCHITECTURE = ROOT / "docs" / "architecture.md"


def dependency_table() -> tuple[dict[str, str], dict[str, set[str]]]:
    """(module path -> layer, layer -> the layers it may import), read from the doc's table."""
    text = ARCHITECTURE.read_text()
    section = text.split("### Dependencies", 1)[1].split("\n#", 1)[0]
    paths, allowed = {}, {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 3 or not cells[1].startswith("`"):
            continue
        layer = cells[0]
        for path in re.findall(r"`([^`]+)`", cells[1]):
            paths[path] = layer
        allowed[layer] = set(re.findall(r"`([^`]+)`", cells[2])) | {layer}
    assert paths and allowed, "docs/architecture.md has no Dependencies table"
    return paths, allowed


def layer_of(path: str, paths: dict[str, str]) -> str | None:
    """The layer of ``path``: its own row, else a pattern's (``*``: one folder), else the
    longest folder's that holds it."""
    if path in paths:
        return paths[path]
    for pattern, layer in paths.items():
        if "*" in pattern and fnmatch.fnmatch(path, pattern) and path.count("/") == pattern.count("/"):
            return layer
    best = max((p for p in paths if p.endswith("/") and path.startswith(p)), key=len, default=None)
    return paths[best] if best else None


def module_file(module: str) -> str | None:
    """The repository path of module ``module`` (a package: its __init__.py), or None."""
    top, _, rest = module.partition(".")
    if top not in PACKAGES:
        return None
    rel = "/".join([PACKAGES[top], *rest.split(".")]) if rest else PACKAGES[top]
    for candidate in (f"{rel}.py", f"{rel}/__init__.py"):
        if (ROOT / candidate).exists():
            return candidate
    return None


def project_imports(path):
    """(line, imported module) for every import of crtk_bridge or crtk_client in file ``path``."""
    rel = path.relative_to(ROOT)
    parts = list(rel.parent.parts)
    package = parts[2:] if parts[:2] == ["clients", "python"] else parts  # the import package's
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] in PACKAGES:
                    yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] not in PACKAGES:
                continue
            for alias in node.names:  # ``from pkg import submodule`` imports the submodule
                sub = f"{target}.{alias.name}"
                yield node.lineno, sub if module_file(sub) else target


def test_every_import_follows_the_documented_dependencies():
    paths, allowed = dependency_table()
    wrong = []
    for path in sorted([*PACKAGE.rglob("*.py"), *CLIENT.rglob("*.py")]):
        rel = str(path.relative_to(ROOT))
        layer = layer_of(rel, paths)
        assert layer is not None, f"{rel} is in no layer of docs/architecture.md's Dependencies table"
        for line, module in project_imports(path):
            target = module_file(module)
            assert target is not None, f"{rel}:{line}: imports {module}, which is not a module of the package"
            to = layer_of(target, paths)
            if to not in allowed[layer]:
                wrong.append(f"{rel}:{line} ({layer}) imports {module} ({to})")
    assert not wrong, "imports the Dependencies table does not allow:\n" + "\n".join(wrong)


def test_the_checker_sees_a_forbidden_import(tmp_path):
    paths, allowed = dependency_table()
    assert layer_of("crtk_bridge/core/loop.py", paths) == "core"
    assert layer_of("crtk_bridge/core/actuator.py", paths) == "seam"
    assert layer_of("crtk_bridge/backends/feetech/tables.py", paths) == "tables"
    assert layer_of("crtk_bridge/backends/feetech/backend.py", paths) == "backends"
    assert layer_of("crtk_bridge/backends/robotiq/tables.py", paths) == "tables"  # a fifth vendor's too
    assert layer_of("crtk_bridge/backends/robotiq/__init__.py", paths) == "tables"
    assert layer_of("crtk_bridge/backends/__init__.py", paths) == "backends"
    assert "backends" not in allowed["core"] and "core" not in allowed["client"] and "core" not in allowed["sim"]
    # the client distribution installs alone: its package imports nothing of crtk_bridge
    assert layer_of("clients/python/crtk_client/device.py", paths) == "client library"
    assert allowed["client library"] == {"client library"}
    assert module_file("crtk_client.device") == "clients/python/crtk_client/device.py"
    assert list(project_imports(CLIENT / "zenoh_link.py"))  # its imports of crtk_client are seen


CITATION = re.compile(r"DESIGN\.md|\.\./shared|(?<![\w/.-])shared/(reference|DESIGN|STYLE|crtk-spec)")


def test_no_product_file_cites_a_document_outside_the_repository():
    # product code cites docs/architecture.md (its sections), never the design notes it was built from
    assert CITATION.search("see ../shared/reference/servos.md") and CITATION.search("(DESIGN.md target)")
    assert CITATION.search("see shared/reference/servos.md sections 1-2")
    assert not CITATION.search("SnapshotBuffer in shared/memory") and not CITATION.search("crtk_bridge/shared/x")
    found = []
    for folder in ("crtk_bridge", "bench", "systemd", "profiles", "docs"):
        for path in sorted((ROOT / folder).rglob("*")):
            if path.is_file() and path.suffix in {".py", ".md", ".yaml", ".service", ".txt", ".urdf", ".cfg", ""}:
                for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                    if CITATION.search(line):
                        found.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    for name in ("README.md", "setup.py", "pyproject.toml"):
        for n, line in enumerate((ROOT / name).read_text().splitlines(), 1):
            if CITATION.search(line):
                found.append(f"{name}:{n}: {line.strip()}")
    assert not found, "cite docs/architecture.md instead:\n" + "\n".join(found)


def test_every_section_the_code_cites_exists():
    headings = {line.lstrip("#").strip() for line in ARCHITECTURE.read_text().splitlines() if line.startswith("#")}
    cited = []
    for folder in ("crtk_bridge", "bench"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            text = " ".join(path.read_text().split())  # a citation may wrap
            for section in re.findall(r'docs/architecture\.md, "([^"]+)"', text):
                cited.append((path.relative_to(ROOT), section))
    assert len(cited) > 10
    missing = [f"{path}: {section!r}" for path, section in cited if section not in headings]
    assert not missing, "cited sections docs/architecture.md does not have:\n" + "\n".join(missing)
