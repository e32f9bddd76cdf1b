"""`fleetslam config` prints every setting as a TOML file that loads back to the defaults,
each key with config.py's comment and its rule; docs/config.md is that reference, generated;
--config and the other global options work before and after the command."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

from fleetslam.config import Config, load_config
from fleetslam.config_reference import REGENERATE, field_comments, reference_markdown
from fleetslam.validation.rules import rules_of

ROOT = Path(__file__).resolve().parents[1]


def fleetslam(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    return subprocess.run([sys.executable, "-m", "fleetslam.cli", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=60)


def test_the_printed_settings_load_back_to_the_defaults(tmp_path):
    done = fleetslam(["config"], tmp_path)
    assert done.returncode == 0, done.stderr
    path = tmp_path / "all.toml"
    path.write_text(done.stdout)
    assert load_config(path) == Config()
    assert list(tmp_path.iterdir()) == [path]
    # Each key: config.py's comment above it (written there once), then its rule.
    lines = done.stdout.splitlines()
    i = lines.index("match_ratio = 0.85")
    assert lines[i - 2:i] == ["# Lowe ratio between best and second-best match.",
                              "# (a number, in (0, 1])"]
    for section in dataclasses.fields(Config):
        cls = type(getattr(Config(), section.name))
        comments = field_comments(cls)
        for key in rules_of(cls):
            at = next(n for n, line in enumerate(lines)
                      if line.startswith((f"{key} = ", f"# {key} =")))
            assert lines[at - 1].startswith("# ("), f"{section.name}.{key} has no rule"
            assert comments.get(key) is not None, f"{section.name}.{key}: no field found"
    assert "# c_total_g =" in lines  # unset (None): left out, as TOML has no null


def test_the_printed_settings_show_the_config_given(tmp_path):
    (tmp_path / "f.toml").write_text("[orb]\nn_features = 500\n")
    done = fleetslam(["config", "--config", "f.toml"], tmp_path)
    assert done.returncode == 0, done.stderr
    assert "n_features = 500" in done.stdout.splitlines()


def test_the_reference_page_is_up_to_date():
    page = (ROOT / "docs" / "config.md").read_text()
    assert page == reference_markdown(), f"docs/config.md is stale: {REGENERATE}"


def test_global_options_are_taken_after_the_command_too(tmp_path):
    """`fleetslam status --config f.toml` reads f.toml (here a bad one: told at once, in one
    line naming file and key, before any network), as `fleetslam --config f.toml status`
    does; given in both places, the one after the command wins."""
    (tmp_path / "bad.toml").write_text("[transport]\nmax_sessions = 0\n")
    (tmp_path / "good.toml").write_text("")
    told = "fleetslam: error: bad.toml: transport.max_sessions = 0: must be at least 1\n"
    for argv in (["status", "--config", "bad.toml"], ["--config", "bad.toml", "status"],
                 ["--config", "good.toml", "status", "--config", "bad.toml"],
                 ["merge", "--quiet", "--config", "bad.toml"]):
        done = fleetslam(argv, tmp_path)
        assert (done.returncode, done.stderr) == (2, told), argv
    done = fleetslam(["status", "--zenoh-config", "missing.json5"], tmp_path)
    assert (done.returncode, done.stderr) == (
        2, "fleetslam: error: missing.json5: no such Zenoh config file\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml", "good.toml"]


def test_the_sections_are_grouped_algorithm_apart_from_deployment():
    """Every section of Config in exactly one group, in Config's order: the printed file and
    the reference page follow it."""
    from fleetslam.config import SECTION_GROUPS

    grouped = [name for names in SECTION_GROUPS.values() for name in names]
    assert grouped == [f.name for f in dataclasses.fields(Config)]
    page = reference_markdown()
    assert [page.index(f"## {group}\n") for group in SECTION_GROUPS] == \
        sorted(page.index(f"## {group}\n") for group in SECTION_GROUPS)


def test_the_decisions_page_names_settings_that_exist_or_were_removed():
    """docs/decisions.md, one section per config section: each setting it names in
    backticks is one of that section's, except those it says were removed (which are not)."""
    import re

    text = (ROOT / "docs" / "decisions.md").read_text()
    parts = re.split(r"^## \[(\w+)\]$", text, flags=re.MULTILINE)
    assert len(parts) > 1
    for section, body in zip(parts[1::2], parts[2::2]):
        known = set(rules_of(type(getattr(Config(), section))))
        removed = set(re.findall(r"\*Removed:\*\s+`(\w+)", body))
        named = set(re.findall(r"`(\w+)[ `]", body))
        assert not removed & known, f"[{section}] says these were removed: {removed & known}"
        # A reason may name a setting of another section (the session budget names the
        # transport's frames in flight, a merge setting a tracking one).
        unknown = {n for n in named - known - removed
                   if not any(n in rules_of(type(getattr(Config(), f.name)))
                              for f in dataclasses.fields(Config))}
        assert not unknown, f"[{section}] names settings that do not exist: {unknown}"
