"""ros.dirs: two suites started from one directory keep their files apart by namespace."""

from __future__ import annotations

from pathlib import Path

import pytest

from t42_transfer.ros.dirs import file_in_namespace, in_namespace


@pytest.mark.parametrize("path, namespace, expected", [
    ("recordings", "/left", "recordings/left"), ("recordings", "/", "recordings"), ("recordings", "", "recordings"),
    ("data/bags", "/lab/left/", "data/bags/lab/left"), ("/abs/bags", "/left", "/abs/bags"),
])
def test_relative_directories_go_under_the_namespace_absolute_ones_stay(path: str, namespace: str,
                                                                        expected: str) -> None:
    assert in_namespace(path, namespace) == Path(expected)


def test_a_relative_file_keeps_its_name_in_the_namespaces_folder() -> None:
    assert file_in_namespace("models/current.safetensors", "/left") == Path("models/left/current.safetensors")
    assert file_in_namespace("/m/current.safetensors", "/left") == Path("/m/current.safetensors")


def test_the_transfer_server_reads_and_writes_its_namespaces_folders() -> None:
    from t42_transfer.nodes.transfer_server import TransferServerParams

    params = TransferServerParams(source_model=Path("/m/source.safetensors"), model_dir=Path("models"),
                                  bag_dir="recordings")
    spec = params.spec("/left")
    assert (spec.model_dir, spec.bag_dir) == (Path("models/left"), Path("recordings/left"))
    assert params.spec("").model_dir == Path("models")
