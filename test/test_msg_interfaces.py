"""t42_interfaces' messages in rosbags' typestore (msg_adapters.interfaces): found installed or in the repository,
and the same types (RIHS01 hashes) as the installed package rclpy publishes."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from rosbags.typesys import Stores, get_typestore

import msg_adapters as ma
from msg_adapters import interfaces
from msg_adapters.kit import INTERFACE_TYPES

MESSAGES = ("BagClosed", "ModelUpdated", "PlanCandidates", "PlanResult")


def test_the_typestore_holds_the_installed_messages_with_rclpys_type_hashes() -> None:
    assert INTERFACE_TYPES == tuple(f"t42_interfaces/msg/{n}" for n in MESSAGES)
    found = interfaces.msg_dir()
    assert found == Path(sys.prefix) / "share" / "t42_interfaces" / "msg"  # the venv's build, not the repository's
    for name in MESSAGES:
        described = json.loads((found / f"{name}.json").read_text())  # what rosidl generated for rclpy
        hashes = {h["type_name"]: h["hash_string"] for h in described["type_hashes"]}
        assert ma.TYPESTORE.hash_rihs01(f"t42_interfaces/msg/{name}") == hashes[f"t42_interfaces/msg/{name}"]


def test_an_unbuilt_checkout_reads_the_repositorys_files(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    assert interfaces.msg_dir() == interfaces.REPOSITORY_INTERFACES / "t42_interfaces" / "msg"
    store = get_typestore(Stores.ROS2_JAZZY)
    assert interfaces.register_interfaces(store) == INTERFACE_TYPES
    for name in INTERFACE_TYPES:
        assert store.hash_rihs01(name) == ma.TYPESTORE.hash_rihs01(name)
    assert interfaces.register_interfaces(store) == ()  # registered once


def test_a_missing_or_broken_package_is_a_warning(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    store = get_typestore(Stores.ROS2_JAZZY)
    assert interfaces.register_interfaces(store, "no_such_interfaces") == ()
    broken = tmp_path / "share" / "broken_interfaces" / "msg"
    broken.mkdir(parents=True)
    (broken / "Bad.msg").write_text("int32[ x\n")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path))
    with pytest.warns(UserWarning, match="Bad.msg"):
        assert interfaces.register_interfaces(store, "broken_interfaces") == ()
