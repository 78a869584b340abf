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
    from t42_transfer.nodes.transfer_server_params import TransferServerParams

    params = TransferServerParams(source_model=Path("/m/source.safetensors"), model_dir=Path("models"),
                                  bag_dir="recordings")
    spec = params.spec("/left")
    assert (spec.model_dir, spec.bag_dir) == (Path("models/left"), Path("recordings/left"))
    assert params.spec("").model_dir == Path("models")


def test_a_directory_is_claimed_by_the_first_namespace_and_refused_to_another(tmp_path: Path) -> None:
    from t42_transfer.ros.dirs import claim, claim_file

    claim(tmp_path / "not_yet", "/left")  # nothing made: its maker claims it
    assert not (tmp_path / "not_yet").exists() and not claim_file(tmp_path / "not_yet").exists()
    (tmp_path / "bags").mkdir()
    claim(tmp_path / "bags", "/left")
    assert claim_file(tmp_path / "bags") == tmp_path / ".bags.t42_namespace"
    assert claim_file(tmp_path / "bags").read_text() == "/left\n" and not list((tmp_path / "bags").iterdir())
    tmp_path = tmp_path / "bags"
    claim(tmp_path, "left/")  # the same namespace, however written, and again after a restart
    with pytest.raises(ValueError, match=r"holds the files of the suite under /left .* a suite under /right .*"
                                         "share_dirs:=true"):
        claim(tmp_path, "/right")
    with pytest.raises(ValueError, match="under /left"):
        claim(tmp_path, "")  # the root namespace is a namespace too
    claim(tmp_path, "/right", share=True)  # asked for: shared, and the claim stays the first one's
    assert claim_file(tmp_path).read_text() == "/left\n"


def test_two_namespaces_recording_into_one_absolute_directory(ros, tmp_path: Path) -> None:
    from t42_transfer.nodes.recorder import Recorder

    shared = str(tmp_path / "bags")
    left = ros.add(Recorder, {"out_dir": shared}, namespace="/left")
    with pytest.raises(ValueError, match=f"/right/recorder: out_dir {shared} holds the files of the suite under /left"):
        ros.add(Recorder, {"out_dir": shared}, namespace="/right")
    right = ros.add(Recorder, {"out_dir": shared, "share_dirs": True}, namespace="/right")
    assert left.out_dir == right.out_dir == Path(shared)


def test_the_transfer_server_refuses_bags_another_namespace_holds(tmp_path: Path) -> None:
    from t42_transfer.nodes.transfer_server_params import TransferServerParams
    from t42_transfer.ros.dirs import claim

    (tmp_path / "bags").mkdir()
    claim(tmp_path / "bags", "/left")
    params = TransferServerParams(source_model=Path("/m/source.safetensors"), model_dir=tmp_path / "models",
                                  bag_dir=str(tmp_path / "bags"))
    with pytest.raises(ValueError, match="held|holds the files of the suite under /left"):
        params.spec("/right")
    assert params.spec("/left").bag_dir == tmp_path / "bags"
