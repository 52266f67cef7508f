"""One protocol vocabulary (issue 8 item 9): the codes in crtk_client/vocabulary.py are exactly
those docs/protocol.md lists, the code uses no other, every layer takes its words from there, and
every exception the project defines derives from CrtkBridgeError."""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import crtk_bridge
import crtk_client
from crtk_bridge import vocabulary as V
from crtk_bridge.errors import CrtkBridgeError

ROOT = Path(__file__).resolve().parent.parent
DOC = (ROOT / "docs" / "protocol.md").read_text()
CLIENT = ROOT / "clients" / "python" / "crtk_client"  # the client distribution's package
SOURCES = sorted([*(ROOT / "crtk_bridge").rglob("*.py"), *CLIENT.rglob("*.py")])


def _section(title: str) -> str:
    return DOC.split(f"## {title}", 1)[1].split("\n## ", 1)[0]


def test_error_codes_are_the_documented_ones():
    documented = set(re.findall(r"^\| `([a-z_]+)` \|", _section("Error codes"), re.M))
    assert documented == set(V.ErrorCode)


def test_event_codes_are_the_documented_ones():
    documented = set()
    for row in re.findall(r"^\| `(?:error|warning|status)` \| ([^|]+) \|", _section("Event codes"), re.M):
        documented |= set(re.findall(r"`([a-z_]+)`", row))
    assert documented == set(V.EventCode)


#: (pattern of a code literal in the source, the vocabulary it must belong to)
_USES = [
    (r"\b(?:Refused|ProtocolError|CommandError)\(\s*\"([a-z_]+)\"", V.ErrorCode),
    (r"\"error\": \{\"code\": \"([a-z_]+)\"", V.ErrorCode),
    (r"\bFault\(\s*\"([a-z_]+)\"", V.EventCode),
    (r"event\(\s*\"(?:status|warning|error)\",\s*\"([a-z_]+)\"", V.EventCode),
    (r"StatusReaction\([^)]*\"(?:status|warning|error)\",\s*\"([a-z_]+)\"", V.EventCode),
    (r"\"event\": \"(?:status|warning|error)\", \"data\": \{[^}]*\"code\": \"([a-z_]+)\"", V.EventCode),
]


def test_the_code_uses_only_vocabulary_codes():
    seen = set()
    for path in SOURCES:
        text = path.read_text()
        for pattern, vocab in _USES:
            for found in re.findall(pattern, text, re.S):
                seen.add(found)
                assert found in set(vocab), f"{path.relative_to(ROOT)}: code {found!r} is not in {vocab.__name__}"
    assert {"bad_request", "read_only", "bus_timeout", "control_released"} <= seen  # the scan finds them


def test_every_layer_takes_its_words_from_the_vocabulary():
    from crtk_bridge.client import connection, device
    from crtk_bridge.core import control as controller, state
    from crtk_bridge.server import protocol

    assert state.OperatingState is V.OperatingState and state.StateCommand is V.StateCommand
    assert controller.STATE_COMMANDS == tuple(V.StateCommand) == protocol.STATE_COMMANDS
    assert protocol.PROTOCOL_VERSION == connection.PROTOCOL_VERSION == V.PROTOCOL_VERSION
    assert f"# crtk-bridge socket protocol, version {V.PROTOCOL_VERSION}" in DOC
    assert set(protocol.TOPICS) == set(V.Topic) and device.JS_TOPICS == V.JOINT_TOPICS
    assert set(device.CARTESIAN_TOPICS) == set(V.CartesianTopic)
    assert set(controller.MOTION_COMMANDS) <= set(V.JointCommand)
    # the vocabulary is neutral: it imports nothing of the project, so every layer may import it
    # crtk_bridge.vocabulary is the client's module (the same object, wherever it is installed:
    # the checkout under an editable install, site-packages under CI's `pip install '.[test]'`)
    import crtk_client.vocabulary
    assert V is crtk_client.vocabulary and Path(V.__file__).parent.name == "crtk_client"
    tree = ast.parse((CLIENT / "vocabulary.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            assert node.level == 0 and not (node.module or "").startswith(("crtk_bridge", "crtk_client")), \
                ast.dump(node)


def test_every_exception_derives_from_crtk_bridge_error():
    defined = []
    for mod in [*pkgutil.walk_packages(crtk_bridge.__path__, "crtk_bridge."),
                *pkgutil.walk_packages(crtk_client.__path__, "crtk_client.")]:
        module = importlib.import_module(mod.name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ == module.__name__ and issubclass(cls, BaseException):
                defined.append(cls)
    assert len(defined) >= 8  # the walk found the project's exceptions
    outside = [f"{c.__module__}.{c.__qualname__}" for c in defined if not issubclass(c, CrtkBridgeError)]
    assert not outside, f"not under CrtkBridgeError: {outside}"
