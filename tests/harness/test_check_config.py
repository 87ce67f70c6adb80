"""`keyframed check-config` from the outside: layering, printed TOML, error lines.

Good and bad files also run against the sanitizer build (any_bin): an ODR clash
between two structs named TelemetryConfig once corrupted the loaded configuration
there and nowhere else.
"""

from __future__ import annotations

import os
import subprocess
import tomllib
from pathlib import Path

from conftest import ROOT


def check(kf_bin: Path, *args: str | Path, env: dict[str, str] | None = None):
    full_env = {k: v for k, v in os.environ.items() if k != "KEYFRAMED_CONFIG_DIR"}
    full_env.update(env or {})
    return subprocess.run(
        [str(kf_bin), "check-config", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=30,
        env=full_env,
    )


def test_shipped_config_is_valid_and_equals_the_defaults(any_bin: Path, tmp_path: Path):
    kf_bin = any_bin
    shipped = check(kf_bin, ROOT / "config/keyframed.toml")
    assert shipped.returncode == 0, shipped.stderr
    assert shipped.stderr == ""  # sanitizer reports land here
    empty = check(kf_bin, "--config-dir", tmp_path)
    assert empty.returncode == 0, empty.stderr
    body = lambda text: text.split("\n", 1)[1]  # noqa: E731 - the header names the sources
    assert body(shipped.stdout) == body(empty.stdout)
    printed = tomllib.loads(shipped.stdout)
    assert tomllib.loads((ROOT / "config/keyframed.toml").read_text()) == printed


def test_layers_and_overrides(kf_bin: Path, tmp_path: Path):
    (tmp_path / "conf.d").mkdir()
    (tmp_path / "keyframed.toml").write_text(
        '[camera]\nfps = 10\nwidth = 640\n[log]\nlevel = "debug"\n'
    )
    (tmp_path / "conf.d/20-b.toml").write_text("[camera]\nfps = 20\n")
    (tmp_path / "conf.d/10-a.toml").write_text('[camera]\nfps = 15\nsource = "libcamera"\n')
    (tmp_path / "conf.d/notes.txt").write_text("[camera]\nfps = 99\n")
    p = check(
        kf_bin, "--config-dir", tmp_path, "--set", "camera.height=480", "--set=zenoh.vehicle=uav7"
    )
    assert p.returncode == 0, p.stderr
    cfg = tomllib.loads(p.stdout)
    assert cfg["camera"] == cfg["camera"] | {
        "fps": 20.0,
        "width": 640,
        "height": 480,
        "source": "libcamera",
    }
    assert cfg["zenoh"]["vehicle"] == "uav7"
    assert cfg["log"]["level"] == "debug"
    assert p.stdout.splitlines()[0] == (
        f"# keyframed configuration from: built-in defaults < {tmp_path}/keyframed.toml"
        f" < {tmp_path}/conf.d/10-a.toml < {tmp_path}/conf.d/20-b.toml"
        " < --set camera.height=480 < --set zenoh.vehicle=uav7"
    )
    # The same directory through the environment, as a unit's Environment= would set it.
    env = check(kf_bin, "--quiet", env={"KEYFRAMED_CONFIG_DIR": str(tmp_path)})
    assert (env.returncode, env.stdout, env.stderr) == (0, "", "")


def test_bad_files_name_file_line_and_key(any_bin: Path, tmp_path: Path):
    kf_bin = any_bin
    (tmp_path / "conf.d").mkdir()
    (tmp_path / "keyframed.toml").write_text('[selection]\nmode = "paper"\ntarget = "high"\n')
    cam = tmp_path / "conf.d/10-cam.toml"
    cam.write_text('[camera]\nsource = "v4l2"\n\nfps = 500\nfsp = 30\n\n[camre]\nx = 1\n')
    broken = tmp_path / "conf.d/20-broken.toml"
    broken.write_text("[log]\nlevel = 'info\n")
    p = check(kf_bin, "--config-dir", tmp_path, "--set", "tagging.jpeg_quality=0")
    assert p.returncode == 1
    assert p.stdout == ""
    lines = p.stderr.splitlines()
    assert lines[:4] == [
        f"keyframed: {tmp_path}/keyframed.toml:3: selection.target: "
        "expected a number, got a string",
        f"keyframed: {cam}:4: camera.fps: must be between 1 and 240 (got 500)",
        f"keyframed: {cam}:5: camera.fsp: unknown key (did you mean 'fps'?)",
        f"keyframed: {cam}:7: camre: unknown section (did you mean 'camera'?)",
    ]
    assert lines[4].startswith(f"keyframed: {broken}:2: "), lines[4]  # the TOML parser's words
    assert lines[5] == (
        "keyframed: --set tagging.jpeg_quality=0: tagging.jpeg_quality: "
        "must be between 1 and 100 (got 0)"
    )
    assert len(lines) == 6


def test_single_file_and_usage_errors(kf_bin: Path, tmp_path: Path):
    good = tmp_path / "good.toml"
    good.write_text('[telemetry]\nurl = "serial:/dev/ttyAMA0:921600"\nautopilot = "1:1"\n')
    p = check(kf_bin, good)
    assert p.returncode == 0, p.stderr
    assert tomllib.loads(p.stdout)["telemetry"]["url"] == "serial:/dev/ttyAMA0:921600"

    missing = check(kf_bin, tmp_path / "missing.toml")
    assert (missing.returncode, missing.stderr) == (
        1,
        f"keyframed: {tmp_path}/missing.toml: no such file\n",
    )
    nodir = check(kf_bin, "--config-dir", tmp_path / "nodir")
    assert nodir.returncode == 1 and "no such directory" in nodir.stderr
    both = check(kf_bin, good, "--config-dir", tmp_path)
    assert both.returncode == 2
    # --set's form is the command line's (2); its key and value, the configuration's (1)
    for form in ("camera.fps", "fps=25", ".fps=25", "camera=fps.25", "a\nb"):
        bad = check(kf_bin, "--set", form)
        assert bad.returncode == 2, (form, bad.returncode, bad.stderr)
        assert len(bad.stderr.splitlines()) == 1, bad.stderr
        assert "expected --set SECTION.KEY=VALUE" in bad.stderr, bad.stderr
    assert "--set a\\nb:" in bad.stderr, bad.stderr  # echoed on its one line
    assert check(kf_bin, "--set", "camera.fsp=25").returncode == 1
    unknown = check(kf_bin, "--frobnicate")
    assert unknown.returncode == 2 and "unknown option --frobnicate" in unknown.stderr
    assert check(kf_bin, "--help").returncode == 0


def test_files_it_names_are_absolute_and_a_zenoh_config_is_read(
    kf_bin: Path, tmp_path: Path
) -> None:
    """check-config reads the Zenoh configuration as zenoh does (a typo found there, not
    by `run` after the camera opened: exit 78, no restart loop), and takes only absolute
    file names from files: the service starts in /, wherever check-config ran."""
    bad = tmp_path / "zenoh.json5"
    bad.write_text("{ mode: 'peer', this is not json5 ")
    p = check(kf_bin, "--config-dir", tmp_path, "--set", f"zenoh.config={bad}")
    assert p.returncode == 1 and f"zenoh.config: zenoh config {bad}" in p.stderr, p.stderr
    assert len(p.stderr.splitlines()) == 1, p.stderr
    # Zenoh's nested error for an endpoint: where in the file, and no place in its sources
    endpoint = tmp_path / "endpoint.json5"
    endpoint.write_text('{ mode: "client", connect: { endpoints: ["garbage"] } }')
    p = check(kf_bin, "--config-dir", tmp_path, "--set", f"zenoh.config={endpoint}")
    assert p.returncode == 1, p.stderr
    assert p.stderr.endswith(
        f"zenoh config {endpoint}: line 1, column 42: Endpoints must be of the form "
        "<protocol>/<address>[?<metadata>][#<config>]: garbage\n"
    ), p.stderr
    r = subprocess.run(
        [str(kf_bin), "run", "--config-dir", str(tmp_path), "--set", f"zenoh.config={bad}",
         "--set", f"output.state_dir={tmp_path / 'state'}"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert r.returncode == 78, r.stderr
    assert not (tmp_path / "state").exists(), "no flight directory for a configuration error"

    good = tmp_path / "good.json5"
    good.write_text('{ mode: "peer" }')
    (tmp_path / "keyframed.toml").write_text('[zenoh]\nconfig = "good.json5"\n')
    rel = check(kf_bin, "--config-dir", tmp_path)
    assert rel.returncode == 1, rel.stderr
    assert 'zenoh.config: must be an absolute path (got "good.json5")' in rel.stderr, rel.stderr
    # On a command line a name is the working directory's, as any other argument.
    (tmp_path / "keyframed.toml").unlink()
    cwd = subprocess.run(
        [str(kf_bin), "check-config", "--config-dir", str(tmp_path), "--set",
         "zenoh.config=good.json5"],
        capture_output=True, text=True, timeout=30, cwd=tmp_path,
    )  # fmt: skip
    assert cwd.returncode == 0, cwd.stderr
    assert tomllib.loads(cwd.stdout)["zenoh"]["config"] == str(good)


def test_a_configuration_printed_to_a_full_disk_is_a_failure(kf_bin: Path, tmp_path: Path):
    """`check-config > effective.toml` with no room for it must not exit 0."""
    env = {k: v for k, v in os.environ.items() if k != "KEYFRAMED_CONFIG_DIR"}
    with open("/dev/full", "w") as full:
        p = subprocess.run(
            [str(kf_bin), "check-config", "--config-dir", str(tmp_path)],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=30,
            env=env,
        )
    assert p.returncode == 1, (p.returncode, p.stderr)
    assert p.stderr == (
        "keyframed: check-config: cannot write standard output: No space left on device\n"
    )
    # --quiet prints nothing, so there is nothing to lose
    with open("/dev/full", "w") as full:
        quiet = subprocess.run(
            [str(kf_bin), "check-config", "--config-dir", str(tmp_path), "--quiet"],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=30,
            env=env,
        )
    assert (quiet.returncode, quiet.stderr) == (0, "")
