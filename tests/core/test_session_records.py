"""session_records: a session bag's prints become WSQ, ISO/IEC 19794-2 and ANSI/NIST-ITL
records, read back with the standards' layouts (``tests/record_readers.py``) and NBIS's WSQ
decoder; bad input is refused or listed with its reason."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from rclpy.serialization import serialize_message
from record_readers import read_ansi_nist, read_iso_19794_2_2005, scalar
from rig_prints import true_rolled_print
from std_msgs.msg import Header

from fingerps_recon.offline.session_records import main
from fingerps_recon.reconstruction.outputs import fingerprint_message
from fingerps_recon.records.wsq_image import MAX_RMS_ERROR, decode_wsq
from fingerps_recon.sessions.session_bag import SessionBagWriter
from fingerps_ros.image_conversion import array_to_image

TOPIC = "/fingerps/fingerprint"


@pytest.fixture(scope="module")
def prints() -> list[np.ndarray]:
    return [true_rolled_print(identity) for identity in (3, 8)]


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory, prints) -> Path:
    bag = tmp_path_factory.mktemp("bags") / "session_1"
    with SessionBagWriter(bag) as writer:
        writer.add_topic(TOPIC, "sensor_msgs/msg/Image", offered_qos_yaml="[]")
        messages = [fingerprint_message(image, Time(sec=100 + k)) for k, image in
                    enumerate(prints)]
        # A print topic message of the wrong encoding: listed with its reason, not written.
        messages.insert(1, array_to_image(np.zeros((8, 8, 3), np.uint8), encoding="rgb8",
                                          header=Header(stamp=Time(sec=101))))
        for k, msg in enumerate(messages):
            writer.write(TOPIC, serialize_message(msg), log_time_ns=k + 1, publish_time_ns=k + 1)
    return bag


def test_each_print_of_a_session_gets_its_records(session: Path, prints, tmp_path: Path,
                                                 capsys) -> None:
    out = tmp_path / "records"
    assert main([str(session), "--out", str(out), "--originating-agency", "LAB7"]) == 0
    listed = json.loads((out / "records.json").read_text())["prints"]
    assert [p["print"] for p in listed] == [1, 2, 3]
    assert "mono8" in listed[1]["reason"] and not (out / "print_2").exists()
    for entry, image in zip((listed[0], listed[2]), prints, strict=True):
        folder = out / entry["folder"]
        assert entry["written"] == ["fingerprint.png", "fingerprint.wsq", "fingerprint.fmr",
                                    "fingerprint.an2"]
        wsq = (folder / "fingerprint.wsq").read_bytes()
        decoded, ppi = decode_wsq(wsq)
        assert ppi == 500 and decoded.shape == image.shape
        assert np.sqrt(np.mean((decoded.astype(np.float64) - image) ** 2)) < MAX_RMS_ERROR
        iso = read_iso_19794_2_2005((folder / "fingerprint.fmr").read_bytes())
        assert len(iso["minutiae"]) == entry["minutiae"] > 0
        transaction = read_ansi_nist((folder / "fingerprint.an2").read_bytes())
        assert [t for t, _ in transaction] == [1, 14, 9]
        assert scalar(transaction[0][1], 8) == "LAB7"
        assert scalar(transaction[0][1], 9) == f"session_1-{entry['print']}"
        assert transaction[1][1][999] == wsq
    assert listed[2]["stamp_ns"] == 101_000_000_000
    assert "print 2: a print is a mono8 image" in capsys.readouterr().out


def test_a_bag_without_prints_is_refused_with_what_to_do(tmp_path: Path, capsys) -> None:
    bag = tmp_path / "empty_session"
    with SessionBagWriter(bag) as writer:
        writer.add_topic("/fingerps/normals", "sensor_msgs/msg/Image", offered_qos_yaml="[]")
    assert main([str(bag), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no fingerprint messages" in err and "fingerprint:=true" in err
    assert not (tmp_path / "o").exists()


def test_the_installed_command_runs(session: Path, tmp_path: Path, installed) -> None:
    run = subprocess.run([str(installed("fingerps_recon", "session_records")), str(session),
                          "--out", str(tmp_path / "r")], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert "3 prints of" in run.stdout
    assert (tmp_path / "r" / "print_3" / "fingerprint.an2").stat().st_size > 0
