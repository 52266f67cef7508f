"""The documentation works in a clone of the repository alone: README.md opens with exactly its two
set-up commands, and every relative link (and every `../path` it quotes) resolves inside the repo.
And it is true: every fenced command of README.md and docs/*.md runs, verbatim, on the simulators
from a folder outside the clone with the non-editable install (or is listed with the reason it
cannot), printing what the doc shows; every refusal a doc quotes is what its command prints."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from .conftest import ROOT
from .doc_commands import (
    Background, Command, DocEnv, How, Scenes, documented_output_pattern, parse_doc, parse_messages, ready_pattern,
    run_to_end)

DOCS = [ROOT / "README.md", ROOT / "systemd" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)|!\[[^\]]*\]\(([^)\s]+)\)")
QUOTED_PARENT = re.compile(r"`(\.\./[^`\s]+)`")
SETUP = ["pip install . && crtk-bridge --profile profiles/so101.yaml --sim",
         "pip install '.[test]' && python -m pytest -q -n 2"]


def _inside_repo(target: Path) -> bool:
    try:
        target.resolve().relative_to(ROOT)
    except ValueError:
        return False
    return target.exists()


def test_docs_found():
    assert len(DOCS) >= 4 and all(d.is_file() for d in DOCS)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_resolves_inside_the_repo(doc):
    text = doc.read_text()
    broken = []
    for m in LINK.finditer(text):
        target = m.group(1) or m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (http:, https:, mailto:) or an anchor in the same page
        path = target.split("#", 1)[0]
        if not _inside_repo(doc.parent / path):
            broken.append(target)
    for m in QUOTED_PARENT.finditer(text):
        if not _inside_repo(doc.parent / m.group(1)):
            broken.append(m.group(1))
    assert not broken, f"{doc.relative_to(ROOT)}: links that do not resolve inside the repository: {broken}"


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces -> '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_anchor_names_a_heading(doc):
    text = doc.read_text()
    broken = []
    for m in LINK.finditer(text):
        target = m.group(1) or m.group(2)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or "#" not in target:
            continue
        path, anchor = target.split("#", 1)
        page = (doc.parent / path) if path else doc
        if page.suffix != ".md" or not page.is_file():
            continue
        in_code = False
        slugs = set()
        for line in page.read_text().splitlines():
            in_code ^= line.startswith("```")
            if not in_code and line.startswith("#"):
                slugs.add(_slug(line.lstrip("#")))
        if anchor not in slugs:
            broken.append(target)
    assert _slug("Calibration (`calibrate`, not a CRTK command)") == "calibration-calibrate-not-a-crtk-command"
    assert not broken, f"{doc.relative_to(ROOT)}: links to headings that do not exist: {broken}"


def test_link_check_catches_a_link_outside_the_repo(tmp_path):
    # the checker itself: the README's old link to ../shared/ would fail it
    assert not _inside_repo(ROOT / "README.md" / ".." / ".." / "shared" / "crtk-spec.txt")
    assert LINK.findall("see [CRTK](../shared/crtk-spec.txt) and ![x](img.png)") == [
        ("../shared/crtk-spec.txt", ""), ("", "img.png")]


def test_readme_opens_with_exactly_its_two_setup_commands():
    text = (ROOT / "README.md").read_text()
    head = text.split("\n---\n", 1)[0]  # the part before the first horizontal rule
    assert head.startswith("# crtk-bridge\n")
    blocks = re.findall(r"```(\w*)\n(.*?)```", head, re.S)
    assert blocks == [("sh", SETUP[0] + "\n"), ("sh", SETUP[1] + "\n")]
    assert "\n## " not in head  # no section before them
    # CI runs the second command verbatim
    assert SETUP[1] in (ROOT / ".ci" / "run").read_text().splitlines()


def test_architecture_is_described_inside_the_repo():
    arch = ROOT / "docs" / "architecture.md"
    assert "(docs/architecture.md)" in (ROOT / "README.md").read_text()
    text = arch.read_text()
    for must in ("front process", "control process", "## Layers", "## The seam"):
        assert must in text


# --------------------------------------------------------------------------------------------
# Every documented command, run as a user runs it (tests/doc_commands.py)

COMMAND_DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "systemd" / "README.md"]
COMMANDS = [c for d in COMMAND_DOCS for c in parse_doc(d)]
MESSAGES = [c for d in COMMAND_DOCS for c in parse_messages(d)]
READY = r"serving CRTK on \S+"  # crtk-bridge's banner once its socket serves


def _my_arm_profile(env: DocEnv) -> None:
    """README 'First time with a real arm', step 2: ``crtk-bridge init-profile so101 my_arm.yaml``
    (in the user's folder, outside the clone)."""
    r = run_to_end(env, Command("README.md", 0, "sh", "", "crtk-bridge init-profile so101 my_arm.yaml --force"), How())
    assert r.rc == 0 and (env.cwd / "my_arm.yaml").is_file(), r.output


def _lerobot_file(env: DocEnv) -> None:
    """my_arm.yaml (README step 2), and what lerobot-calibrate leaves for that arm."""
    _my_arm_profile(env)
    _lerobot_json(env)


def _lerobot_json(env: DocEnv) -> None:
    """What lerobot-calibrate leaves for an arm with id my_arm (docs/calibration.md's path)."""
    import json

    from .test_calibrate_import import LEROBOT

    path = env.home / ".cache/huggingface/lerobot/calibration/robots/so_follower/my_arm.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(LEROBOT, indent=4))


def _imported(env: DocEnv) -> None:
    import yaml

    from .test_calibrate_import import LEROBOT

    joints = {j["name"]: j for j in yaml.safe_load((env.cwd / "my_arm.yaml").read_text())["joints"]}
    lo, hi = LEROBOT["shoulder_pan"]["range_min"], LEROBOT["shoulder_pan"]["range_max"]
    cal = joints["shoulder_pan"]["calibration"]
    assert cal["offset"] == (lo + hi) // 2 and list(cal["range"]) == [lo, hi], cal


HARDWARE = ("needs the arm on backend.port (/dev/ttyACM0); tests/test_setup_servos.py, test_check_scan.py and "
            "test_installed.py run these commands on crtk-sim")
ROS = "needs ROS 2 with rmw_zenoh (not installed here); tests/test_zenoh_ros.py checks the ROS key layout"
LEROBOT = ("LeRobot in a venv of its own (torch: several GB) with the real arms: tests/lerobot/ builds that venv from "
           "tests/lerobot/requirements.txt, installs this plugin into it and runs these commands on simulated arms "
           "(test_lerobot_so101.py, test_lerobot_ur5e.py)")
LEROBOT_INSTALL = ("installs LeRobot (several GB) into the user's own venv: tests/lerobot/venv.py builds that venv and "
                   "installs ./clients/python and ./lerobot_robot_crtk into it, as here")

#: Which daemons each section's commands need, by (doc, heading); a command's own SPEC entry wins.
SCENES = {
    ("README.md", "Driving the robot"): "so101",
    ("docs/calibration.md", "From LeRobot: `crtk-ctl calibrate --import`"): "so101",
    ("README.md", "First time with a real arm"): "first-time",
    ("docs/cartesian.md", "Conventions"): "so101",
    ("docs/zenoh.md", "Remote clients (Python and crtk-ctl)"): "zenoh",
    ("docs/simulators.md", "`crtk-sim canopen`"): "sim-canopen",
    ("docs/teleop.md", "Teleoperation: a leader arm drives a follower"): "teleop",
    ("docs/recording.md", "Commands"): "so101",
    ("docs/recording.md", "Replay and plots"): "so101",  # after Commands (doc order): run2.mcap exists
}

#: The reviewed list: how each documented command runs when not simply to exit status 0 in its
#: section's scene, and why a command cannot run here. Keyed by (doc, the command's first line).
SPEC: dict[tuple[str, str], How] = {
    # README.md
    ("README.md", "pip install . && crtk-bridge --profile profiles/so101.yaml --sim"): How(
        "daemon", "so101", ready=READY, run="crtk-bridge --profile profiles/so101.yaml --sim",
        why="`pip install .` is the install under test (DocEnv.bin_dir)"),
    ("README.md", "pip install '.[test]' && python -m pytest -q -n 2"): How(
        "skip", why="the test suite itself: CI runs it verbatim (.ci/run; test_readme_opens_with_exactly_its_two_setup_commands)"),
    ("README.md", "crtk-ctl state"): How(scene="so101", out=(r"so101: DISABLED\s+homed: yes\s+busy: no",)),
    ("README.md", "crtk-ctl enable"): How(scene="so101", out=(r"so101: ENABLED",)),
    ("README.md", "crtk-ctl move_jp 0.1 0.2 0.3 0 0 --wait"): How(scene="so101", out=(r"so101: move_jp done",)),
    ("README.md", "crtk-ctl get measured_js"): How(
        scene="so101", out=(r"shoulder_pan\s+\+0\.(09|10)\d* rad", r"elbow_flex\s+\+0\.(29|30)\d* rad")),
    ("README.md", "crtk-ctl echo measured_js --rate 50"): How(
        "forever", "so101", ready=r"shoulder_pan=[+-]\d.*\n.*shoulder_pan=[+-]\d", rc=130),  # two frames
    ("README.md", "crtk-ctl --ns so101/gripper move_jp 0.5 --wait"): How(scene="so101", out=(r"so101/gripper: move_jp done",)),
    ("README.md", "crtk-ctl get measured_cp"): How(scene="so101", out=(r"position .* m \(x y z\)", r"orientation .*\(qx qy qz qw\)")),
    ("README.md", "crtk-ctl events"): How(
        "forever", "so101", ready=r"status\s+state_changed\s+so101: PAUSED", rc=130,
        trigger="crtk-ctl pause && crtk-ctl resume"),
    ("README.md", "crtk-ctl disable"): How(scene="so101", out=(r"so101: DISABLED",)),
    ("README.md", "crtk-ctl list"): How(scene="so101", out=(r"(?m)^so101/gripper:$", r"joints:\s+shoulder_pan, shoulder_lift")),
    ("README.md", "crtk-bridge check --profile my_arm.yaml --scan"): How(
        scene="first-time", out=(r"6 servos answered", r"id\s+6\s+gripper\s+sts3215")),
    ("README.md", "crtk-ctl calibrate --profile my_arm.yaml --import "
                  "~/.cache/huggingface/lerobot/calibration/robots/so_follower/my_arm.json"): How(
        scene="first-time", setup=_lerobot_json, after=_imported),
    ("README.md", "crtk-bridge check --profile profiles/so101.yaml"): How(),
    ("README.md", "crtk-bridge setup-servos --profile profiles/so101.yaml"): How("skip", why=HARDWARE),
    ("README.md", "crtk-bridge check --profile profiles/so101.yaml --scan"): How("skip", why=HARDWARE),
    ("README.md", "crtk-bridge check --profile profiles/so101.yaml --scan --json"): How("skip", why=HARDWARE),
    ("README.md", "crtk-bridge --profile profiles/so101.yaml"): How("skip", why=HARDWARE),
    # docs/calibration.md
    ("docs/calibration.md", "crtk-ctl calibrate --profile my_arm.yaml"): How(
        "skip", why="interactive: you move every joint by hand (tests/test_calibrate_sim.py drives it with a simulated hand)"),
    ("docs/calibration.md", "crtk-ctl calibrate --profile my_arm.yaml --import "
                            "~/.cache/huggingface/lerobot/calibration/robots/so_follower/my_arm.json"): How(
        scene="so101", setup=_lerobot_file, after=_imported),
    # docs/cartesian.md: the body frame from crtk-ctl
    ("docs/cartesian.md", "crtk-ctl get measured_cv --frame body"): How(
        scene="so101", out=(r"so101 measured_cv \(body\)\s+stamp \d", r"gripper_frame_link in gripper_frame_link")),
    ("docs/cartesian.md", "crtk-ctl echo measured_cv --frame body --count 3"): How(
        scene="so101", out=(r"\A(\d+\.\d+  v=.*  w=.*\n){3}\Z",)),
    # docs/simulators.md
    ("docs/simulators.md", "crtk-sim feetech --profile profiles/so101.yaml --link /tmp/ttySIM --control /tmp/sim.sock"): How(
        "forever", ready=r"crtk-sim: feetech bus ready: port=\S+/ttySIM .*ids=1,2,3,4,5,6 baud=1000000", rc=0),
    ("docs/simulators.md", "crtk-sim canopen --profile profiles/canopen_2axis.yaml --link /tmp/ttyCAN --control /tmp/can.sock"): How(
        "daemon", "sim-canopen"),
    ("docs/simulators.md", "crtk-sim ur --profile profiles/ur5e.yaml --host 127.0.0.2 --control /tmp/ur.ctl"): How(
        "forever", rc=0),
    ("docs/simulators.md", "crtk-sim robotiq --profile profiles/robotiq_2f85.yaml --link /tmp/ttyGRIP --control /tmp/grip.sock"): How(
        "forever", ready=r"crtk-sim: robotiq ready: port=\S+/ttyGRIP control=\S+/grip.sock", rc=0),
    # docs/teleop.md (its `crtk-bridge ... &` lines: the scene's daemons, by the rule in how())
    ("docs/teleop.md", "crtk-ctl --robot so101 enable"): How(scene="teleop", out=(r"so101: ENABLED",)),
    ("docs/teleop.md", "crtk-ctl teleop --leader so101_leader --follower so101"): How(
        "forever", "teleop", ready=r"ALIGNING|ENABLED", rc=130),
    # docs/zenoh.md
    ("docs/zenoh.md", "zenohd -l tcp/127.0.0.1:7447 --no-multicast-scouting"): How(
        "skip", why="zenohd is not installed here (not a Python package): the Python router of the same section stands in"),
    ("docs/zenoh.md", "import zenoh"): How("daemon", "zenoh", ready=r"doc_python: ready", start=-1),
    ("docs/zenoh.md", "crtk-bridge --profile profiles/so101.yaml --sim --zenoh-connect tcp/127.0.0.1:7447"): How(
        "daemon", "zenoh", ready=READY),
    ("docs/zenoh.md", "crtk-bridge --profile profiles/koch.yaml --sim --zenoh-connect tcp/127.0.0.1:7447 "
                      "--zenoh-listen tcp/127.0.0.1:7448"): How(
        "daemon", "zenoh", ready=READY),
    ("docs/zenoh.md", "crtk-bridge --profile profiles/so101.yaml --zenoh-connect tcp/127.0.0.1:7447 --ros-domain-id 3"): How(
        "skip", why=HARDWARE + "; and a second so101 on one Zenoh network is refused (the --sim one above)"),
    ("docs/zenoh.md", "crtk-ctl --zenoh-connect tcp/127.0.0.1:7447 robots"): How(
        scene="zenoh", out=(r"(?m)^koch$", r"(?m)^so101$")),
    ("docs/zenoh.md", "crtk-ctl --zenoh-connect tcp/127.0.0.1:7447 --robot so101 echo measured_js --rate 50"): How(
        "forever", "zenoh", ready=r"shoulder_pan=.*\n.*shoulder_pan=", rc=130),
    ("docs/zenoh.md", "ros2 run rmw_zenoh_cpp rmw_zenohd"): How("skip", why=ROS),
    ("docs/zenoh.md", "crtk-bridge --profile profiles/so101.yaml --zenoh-connect tcp/127.0.0.1:7447"): How("skip", why=HARDWARE),
    ("docs/zenoh.md", "export RMW_IMPLEMENTATION=rmw_zenoh_cpp"): How("skip", why=ROS),
    ("docs/zenoh.md", "ros2 topic list"): How("skip", why=ROS),
    ("docs/zenoh.md", "ros2 topic echo /so101/measured_js"): How("skip", why=ROS),
    ("docs/zenoh.md", 'ros2 topic pub --once /so101/state_command crtk_msgs/msg/StringStamped "{string: enable}"'): How(
        "skip", why=ROS),
    ("docs/zenoh.md", "python3 my_crtk_script.py"): How("skip", why=ROS + "; the script is the user's own"),
    ("docs/zenoh.md", "crtk-ctl --zenoh-connect tls/so101-pc.lab.example.org:7447 --zenoh-config client.json5 "
                      "--robot so101 state"): How(
        "skip", why="a TLS endpoint on another host, with the lab's certificates (tests/test_zenoh_client_config.py "
                    "checks --zenoh-config)"),
    # recording (README.md, docs/recording.md)
    ("README.md", "crtk-ctl record demo.mcap --duration 2"): How(
        scene="so101", out=(r"demo/demo\.mcap: \d+ cycles \(cycles \d+\.\.\d+\), lost 0",)),
    ("docs/recording.md", "crtk-ctl record run1.mcap"): How(
        "forever", "so101", ready=r"recording \S+/run1/run1\.mcap \(Ctrl-C to stop\)", rc=0),
    ("docs/recording.md", "crtk-ctl record run2.mcap --duration 2"): How(
        scene="so101", out=(r"run2/run2\.mcap: \d+ cycles \(cycles \d+\.\.\d+\), lost 0",)),
    ("docs/recording.md", "crtk-ctl blackbox now.mcap"): How(
        scene="so101", out=(r"now/now\.mcap: \d+ cycles \(cycles \d+\.\.\d+, \d+\.\d s\)",)),
    ("docs/recording.md", "crtk-bridge --profile profiles/so101.yaml --record /data/so101"): How(
        "skip", why=HARDWARE + "; tests/test_recording.py runs --record on --sim"),
    ("docs/recording.md", "crtk-ctl enable"): How(scene="so101", out=(r"so101: ENABLED",)),
    ("docs/recording.md", "crtk-ctl replay run2.mcap --topic measured_js --yes"): How(
        scene="so101", out=(r"first a move_jp to its first position", r"so101: replayed \d+\.\d+ s of measured_js")),
    ("docs/recording.md", "crtk-ctl plot run2.mcap -o run2.png"): How(scene="so101", out=(r"wrote run2\.png",)),
    ("docs/recording.md", "crtk-ctl plot run2.mcap -o run2.html --joints shoulder_pan elbow_flex --from 0.5 --to 1.5"):
        How(scene="so101", out=(r"wrote run2\.html",)),
    ("docs/recording.md", "crtk-ctl disable"): How(scene="so101", out=(r"so101: DISABLED",)),
    ("docs/recording.md", "crtk-bridge --profile profiles/so101.yaml --sim --foxglove-listen 127.0.0.1:8765"): How(
        "skip", why="the so101 scene's daemon has the robot's socket, and 8765 is a fixed port a parallel run would "
                    "take: tests/test_foxglove_live.py starts this daemon on a free port and reads it with a "
                    "Foxglove WebSocket client"),
    # docs/lerobot.md: LeRobot with real arms (tests/lerobot/ runs the same on simulated arms)
    ("docs/lerobot.md", "python3 -m venv ~/lerobot-venv && . ~/lerobot-venv/bin/activate"): How("skip", why=LEROBOT_INSTALL),
    ("docs/lerobot.md", "pip install 'lerobot[feetech]>=0.4.3' ./clients/python ./lerobot_robot_crtk"): How(
        "skip", why=LEROBOT_INSTALL),
    ("docs/lerobot.md", "crtk-bridge --profile follower.yaml &"): How("skip", why=HARDWARE),
    ("docs/lerobot.md", "crtk-bridge --profile leader.yaml &"): How("skip", why=HARDWARE.replace("ttyACM0", "ttyACM1")),
    ("docs/lerobot.md", "crtk-bridge --profile ur5e.yaml &"): How(
        "skip", why="needs a UR5e at backend.host; tests/lerobot/test_lerobot_ur5e.py runs the daemon on crtk-sim ur"),
    ("docs/lerobot.md", "lerobot-teleoperate --robot.type=crtk --robot.robot=so101 --teleop.type=crtk "
                        "--teleop.robot=so101_leader"): How("skip", why=LEROBOT),
    ("docs/lerobot.md", "lerobot-record --robot.type=crtk --robot.robot=so101 --teleop.type=crtk "
                        "--teleop.robot=so101_leader --dataset.repo_id=$HF_USER/so101_pick "
                        '--dataset.single_task="Pick the cube" --dataset.num_episodes=10 --dataset.episode_time_s=30 '
                        "--dataset.reset_time_s=10 --dataset.push_to_hub=false"): How("skip", why=LEROBOT),
    ("docs/lerobot.md", "lerobot-replay --robot.type=crtk --robot.robot=so101 --dataset.repo_id=$HF_USER/so101_pick "
                        "--dataset.episode=0"): How("skip", why=LEROBOT),
    ("docs/lerobot.md", "lerobot-record --robot.type=crtk --robot.robot=so101 --policy.path=$HF_USER/act_so101_pick "
                        '--dataset.repo_id=$HF_USER/eval_so101_pick --dataset.single_task="Pick the cube" '
                        "--dataset.num_episodes=5 --dataset.push_to_hub=false"):
        How("skip", why="a trained policy from the hub, on the real arm; " + LEROBOT),
    ("docs/lerobot.md", "lerobot-replay --robot.type=crtk --robot.robot=ur5e --robot.units=si "
                        "--dataset.repo_id=$HF_USER/ur5e_demo --dataset.episode=0"): How("skip", why=LEROBOT),
    ("docs/lerobot.md", "lerobot-record --robot.type=crtk --robot.robot=ur5e --robot.units=si --teleop.type=crtk "
                        "--teleop.robot=ur5e_leader --teleop.units=si --dataset.repo_id=$HF_USER/ur5e_demo "
                        '--dataset.single_task="Reach" --dataset.push_to_hub=false'): How("skip", why=LEROBOT),
    # systemd/README.md
    ("systemd/README.md", "journalctl -u crtk-bridge@so101 -f"): How("skip", why="the journal of an installed systemd unit"),
    ("systemd/README.md", "journalctl -u 'crtk-bridge@*' -b"): How("skip", why="the journal of an installed systemd unit"),
}

#: The refusals the docs quote (unlabelled fences): the command that prints each, keyed by (doc,
#: the message's start). Scene ``bare``: no daemon at all (nothing on the Zenoh ports either).
MESSAGE_SPEC: dict[tuple[str, str], How] = {
    ("docs/teleop.md", "crtk-ctl teleop: error: argument --tolerance"): How(
        run="crtk-ctl teleop --leader so101_leader --follower so101 --tolerance 0.5", rc=2, scene="bare"),
    ("docs/teleop.md", "crtk-ctl: --rate (rate_hz): must be from 10 to 200 Hz"): How(
        run="crtk-ctl teleop --leader so101_leader --follower so101 --rate 1000", rc=1, scene="teleop"),
    ("docs/zenoh.md", "crtk-bridge: so101: cannot reach the Zenoh router"): How(
        run="crtk-bridge --profile profiles/so101.yaml --sim --zenoh-connect tcp/127.0.0.1:7447", rc=1, scene="bare"),
    ("docs/zenoh.md", "crtk-ctl: crtk-bridge client: cannot reach the Zenoh"): How(
        run="crtk-ctl --zenoh-connect tcp/127.0.0.1:7447 robots", rc=2, scene="bare"),
    ("docs/zenoh.md", "crtk-bridge: so101: transport.zenoh.listen (--zenoh-l"): How(
        "skip", why="a daemon asked to listen on 0.0.0.0 (beyond loopback, if the refusal broke): "
                    "test_zenoh_exposure_refusal_reads_as_documented checks the message in-process"),
}

#: Scenes whose commands wait for another item of issue 18: xfail(strict=True), so they flip (and
#: fail as XPASS, to be removed from here) once that item is merged.
PENDING_SCENES: dict[str, str] = {}  # e.g. {"teleop": "9 (pkg: leader profiles)"}, until it merged

SCENE_ORDER = ["none", "so101", "first-time", "sim-canopen", "zenoh", "bare", "teleop"]


def spec_key(cmd: Command) -> tuple[str, str]:
    return (cmd.doc, cmd.text.split("\n", 1)[0])


def how(cmd: Command) -> How:
    """The command's SPEC entry (in its section's scene, if the section has one), else: run to exit
    status 0 in its section's scene."""
    h = SPEC.get(spec_key(cmd))
    scene = SCENES.get((cmd.doc, cmd.heading))
    if h is not None:
        # the same command in two sections (README's `crtk-ctl state`) runs in each one's scene
        return dataclasses.replace(h, scene=scene) if scene and h.kind in ("run", "forever") else h
    if scene is None:
        raise KeyError(f"{cmd.id}: `{cmd.text}` (section {cmd.heading!r}) has no entry in tests/test_docs.py: "
                       "add its section to SCENES (which daemons it needs) or the command to SPEC (how it runs, "
                       "or why it cannot)")
    if cmd.lang == "sh" and cmd.text.endswith("&"):  # a job the section starts in the background
        if cmd.text.startswith("crtk-bridge "):
            return How("job", scene, ready=READY)
        if cmd.text.startswith("crtk-sim "):
            return How("job", scene, ready=r"crtk-sim: .* ready: ")
    return How(scene=scene)


def pending(h: How) -> str:
    """The issue-18 item a command waits for: its own, or its scene's."""
    return h.item or PENDING_SCENES.get(h.scene, "")


def _ordered(commands: list[Command]) -> list[Command]:
    def rank(c: Command) -> int:
        try:
            return SCENE_ORDER.index(how(c).scene)
        except (KeyError, ValueError):
            return len(SCENE_ORDER)
    return sorted(commands, key=rank)  # stable: doc order within a scene


def _param(cmd: Command):
    try:
        h = how(cmd)
    except KeyError:
        return pytest.param(cmd, id=cmd.id)  # fails, saying what to add
    marks = []
    if h.kind == "skip":
        marks.append(pytest.mark.skip(reason=f"{cmd.id}: {h.why}"))
    if pending(h):
        marks.append(pytest.mark.xfail(strict=True, reason=f"pending issue 18 item {pending(h)}"))
    return pytest.param(cmd, id=f"{cmd.id} {cmd.text.splitlines()[0][:60]}", marks=marks)


def test_every_documented_command_is_in_the_reviewed_list():
    """Each command belongs to a section with a scene or has its own SPEC entry, and each SPEC
    entry still names a documented command (a changed doc line must be reviewed again)."""
    missing = []
    for c in COMMANDS:
        try:
            how(c)
        except KeyError as e:
            missing.append(str(e))
    keys = {spec_key(c) for c in COMMANDS}
    stale = [k for k in SPEC if k not in keys]
    assert not missing and not stale, "\n".join(missing + [f"SPEC entry for a command no doc has: {k}" for k in stale])
    assert all(h.scene in SCENE_ORDER for h in [*SPEC.values(), *MESSAGE_SPEC.values()])
    assert set(SCENES.values()) <= set(SCENE_ORDER)


def message_how(msg: Command) -> How:
    for (doc, start), h in MESSAGE_SPEC.items():
        if doc == msg.doc and msg.text.startswith(start):
            return h
    raise KeyError(f"{msg.id}: the quoted message `{msg.text[:60]}...` has no entry in MESSAGE_SPEC "
                   "(tests/test_docs.py): name the command that prints it")


def test_every_quoted_message_is_in_the_reviewed_list():
    missing = []
    for m in MESSAGES:
        try:
            message_how(m)
        except KeyError as e:
            missing.append(str(e))
    stale = [k for k in MESSAGE_SPEC if not any(m.doc == k[0] and m.text.startswith(k[1]) for m in MESSAGES)]
    assert not missing and not stale, "\n".join(missing + [f"MESSAGE_SPEC entry no doc quotes: {k}" for k in stale])


def test_zenoh_exposure_refusal_reads_as_documented():
    from crtk_bridge.transport.zenoh_session import ZenohConfig, ZenohConfigError, check_exposure

    quoted = next(m.text for m in MESSAGES if "reaches beyond this PC" in m.text)
    with pytest.raises(ZenohConfigError) as info:
        check_exposure(ZenohConfig(listen=["tcp/0.0.0.0:7447"]), "so101")
    assert quoted == f"crtk-bridge: {info.value}"


def test_command_parser_reads_notes_continuations_and_shown_output(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("# T\n\n## S\n\n```sh\ncrtk-ctl state   # DISABLED\ncrtk-ctl calibrate --profile a.yaml \\\n"
                   "    --import b.json\ncrtk-sim x --link /tmp/t\n# crtk-sim: x ready\n```\n\n"
                   "```console\n$ crtk-ctl robots\nkoch\nso101\n```\n\n```python\nx = 1\n```\n\n```\nnot a command\n```\n")
    got = parse_doc(doc, tmp_path)
    assert [(c.line, c.heading, c.text, c.note, c.output) for c in got] == [
        (6, "S", "crtk-ctl state", "DISABLED", ()),
        (7, "S", "crtk-ctl calibrate --profile a.yaml --import b.json", "", ()),
        (9, "S", "crtk-sim x --link /tmp/t", "", ("crtk-sim: x ready",)),
        (14, "S", "crtk-ctl robots", "", ("koch", "so101")),
        (20, "S", "x = 1\n", "", ())]
    assert got[-1].lang == "python"


def test_python_example_comments_are_checked(tmp_path):
    """doc_python.py: an expression whose comment is a literal must evaluate to it."""
    import subprocess
    import sys

    from .doc_commands import PYTHON_DRIVER

    ok, bad = tmp_path / "ok.py", tmp_path / "bad.py"
    ok.write_text("x = [1]   # a note\nsorted(['b', 'a'])   # ['a', 'b']\n")
    bad.write_text("sorted(['b'])   # ['a', 'b']\n")
    assert subprocess.run([sys.executable, str(PYTHON_DRIVER), str(ok)]).returncode == 0
    p = subprocess.run([sys.executable, str(PYTHON_DRIVER), str(bad)], capture_output=True, text=True)
    assert p.returncode == 1 and "gave ['b'], the comment promises ['a', 'b']" in p.stderr


@pytest.fixture(scope="module")
def doc_env(installed):
    """Where the documented commands run, as a user runs them: the console scripts of the
    non-editable install (tests/conftest.py ``installed``), from a folder outside the clone (also
    the commands naming ``profiles/...``: the shipped profiles resolve from any folder). Fixed
    resources a parallel run would share are made private: the Zenoh ports 7447 / 7448, ``/tmp/``
    paths, 127.0.0.2."""
    import shutil
    import tempfile

    from crtk_bridge.sim.loopback import free_loopback_host

    from .conftest import free_port

    tmp = Path(tempfile.mkdtemp(prefix="crtk-doc-"))  # short: Unix socket paths stay under 108 bytes
    (tmp / "t").mkdir()
    subst = {"127.0.0.1:7447": f"127.0.0.1:{free_port()}", "127.0.0.1:7448": f"127.0.0.1:{free_port()}",
             "/tmp/": f"{tmp}/t/", "127.0.0.2": free_loopback_host((30004, 29999, 30003, 30001, 30002))}
    yield DocEnv.create(tmp, bin_dir=installed.bin, subst=subst)
    shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def scenes(doc_env):
    logs = doc_env.cwd.parent / "logs"
    logs.mkdir(exist_ok=True)
    s = Scenes(doc_env, COMMANDS, how, logs)
    yield s
    s.close()


def _trigger_until(env: DocEnv, job: Background, h: How, deadline_s: float = 20.0) -> None:
    """Run ``h.trigger`` until ``job`` prints ``h.ready`` (the job may subscribe after the first)."""
    import time

    trigger = Command("(trigger)", 0, "sh", "", h.trigger)
    deadline = time.monotonic() + deadline_s
    while not re.search(h.ready, job.output()):
        r = run_to_end(env, trigger, How())
        assert r.rc == 0, f"trigger `{h.trigger}` exited {r.rc}:\n{r.output}"
        if time.monotonic() > deadline:
            break
        time.sleep(0.2)


def _section(doc: str, heading: str) -> str:
    text = (ROOT / doc).read_text()
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def _exchange(path: Path, request: dict, frames: int = 0, timeout: float = 10.0) -> tuple[dict, list[dict]]:
    """One request on a fresh socket session: its reply, and the first ``frames`` stream frames."""
    import json
    import socket

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        s.sendall((json.dumps({"id": 1, **request}) + "\n").encode())
        reply, got = None, []
        for line in s.makefile("rb"):
            msg = json.loads(line)
            if msg.get("id") == 1:
                reply = msg
            elif "topic" in msg:
                got.append(msg)
            if reply is not None and (not reply.get("ok") or len(got) >= frames):
                return reply, got
    raise AssertionError(f"no reply to {request}")


TOPIC_WORD = re.compile(r"`((?:measured|setpoint|goal)_(?:js|cp|cv|cf)|operating_state|period_statistics)`")


def test_protocol_subscriptions_name_every_topic_list_advertises(doc_env, scenes):
    """docs/protocol.md, Subscriptions: the topics it names are those `list` advertises (it named
    5 while the SO-101's arm streams 12), and each streams, twists and wrenches also from
    ``<ns>/body`` as it says."""
    scenes.enter("so101")
    sock = doc_env.runtime / "crtk-bridge" / "so101.sock"
    described, _ = _exchange(sock, {"cmd": "list"})
    advertised = {t for ns in described["data"]["namespaces"] for t in ns["topics"]}
    named = set(TOPIC_WORD.findall(_section("docs/protocol.md", "Subscriptions (streams)")))
    assert advertised <= named, f"docs/protocol.md, Subscriptions, omits {sorted(advertised - named)}"
    assert named - advertised <= {"setpoint_cf"}, sorted(named - advertised)  # effort control only: not the SO-101
    for ns in described["data"]["namespaces"]:
        for topic in ns["topics"]:
            where = [ns["name"]] + ([f"{ns['name']}/body"] if topic[-2:] in ("cv", "cf") else [])
            for name in where:
                reply, frames = _exchange(sock, {"cmd": "subscribe", "ns": name,
                                                 "data": {"topic": topic, "rate_hz": 50}}, frames=1)
                assert reply["ok"] and frames[0]["topic"] == topic, (name, topic, reply)


@pytest.mark.parametrize("cmd", [_param(c) for c in _ordered(COMMANDS)])
def test_documented_command_runs(cmd: Command, doc_env: DocEnv, scenes: Scenes):
    """Each fenced command of README.md and docs/*.md, verbatim, on the simulators: its exit
    status, and the output its doc shows or its SPEC entry promises."""

    h = how(cmd)
    if h.scene != "none" or h.kind == "daemon":
        scenes.enter(h.scene)
    if h.setup is not None and h.kind != "daemon":
        h.setup(doc_env)
    if h.kind == "daemon":
        out = scenes.daemon(cmd).output()
    elif h.kind == "job":
        out = scenes.job(cmd, h).output()
    elif h.kind == "forever":
        job = Background(doc_env, cmd, h, doc_env.cwd.parent / "logs" / f"{Path(cmd.doc).stem}-{cmd.line}.log")
        try:
            if h.trigger:
                _trigger_until(doc_env, job, h)
            job.wait_ready(ready_pattern(cmd, h, doc_env))
        finally:
            rc = job.interrupt()
        out = job.output()
        assert rc == h.rc, f"{cmd.id}: `{cmd.text}` exited {rc} on Ctrl-C (documented: {h.rc}):\n{out}"
    else:
        r = run_to_end(doc_env, cmd, h)
        out = r.output
        assert r.rc == h.rc, f"{cmd.id}: `{doc_env.text(cmd, h)}` exited {r.rc}, not {h.rc}:\n{out}"
    for line in cmd.output:
        assert documented_output_pattern(line, doc_env.subst).search(out), \
            f"{cmd.id}: `{cmd.text}` did not print what the doc shows:\n  {line}\nit printed:\n{out}"
    for pattern in h.out:
        assert re.search(pattern, out), f"{cmd.id}: `{cmd.text}`: no /{pattern}/ in:\n{out}"
    if h.after is not None:
        h.after(doc_env)


def _message_param(msg: Command):
    try:
        h = message_how(msg)
    except KeyError:
        return pytest.param(msg, id=msg.id)
    marks = [pytest.mark.skip(reason=f"{msg.id}: {h.why}")] if h.kind == "skip" else []
    if pending(h):
        marks.append(pytest.mark.xfail(strict=True, reason=f"pending issue 18 item {pending(h)}"))
    return pytest.param(msg, id=f"{msg.id} {msg.text[:50]}", marks=marks)


def _message_rank(msg: Command) -> int:
    try:
        return SCENE_ORDER.index(message_how(msg).scene)
    except (KeyError, ValueError):
        return len(SCENE_ORDER)


@pytest.mark.parametrize("msg", [_message_param(m) for m in sorted(MESSAGES, key=_message_rank)])
def test_quoted_message_is_what_the_command_prints(msg: Command, doc_env: DocEnv, scenes: Scenes):
    """Each refusal a doc quotes is, verbatim, what its command prints, with the exit status the
    doc gives."""
    h = message_how(msg)
    scenes.enter(h.scene, jobs=True)
    cmd = Command(msg.doc, msg.line, "sh", msg.heading, h.run, output=(msg.text,))
    r = run_to_end(doc_env, cmd, h)
    assert r.rc == h.rc, f"{msg.id}: `{doc_env.text(cmd, h)}` exited {r.rc}, not {h.rc}:\n{r.output}"
    assert documented_output_pattern(msg.text, doc_env.subst).search(r.output), \
        f"{msg.id}: `{h.run}` printed:\n{r.output}\nnot what the doc quotes:\n{msg.text}"
