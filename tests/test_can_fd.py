"""CAN FD frame lengths (ISO 11898-1:2015) and their analysis, against hand-computed frames.

Base format, ``n`` data bytes (see flowrt.analysis.can_frames): arbitration phase 34 bits
(17 header bits, 4 worst-case stuff bits, 13 from the CRC delimiter to the interframe space);
data phase ESI + DLC (5) + 8n + dynamic stuff bits floor((22 + 8n - 1)/4) - 4 + stuff count
(4) + CRC (17 up to 16 bytes, else 21) + fixed stuff bits (6 or 7). By hand:

- 8 bytes:  5 + 64 + (21 - 4) + 4 + 17 + 6 = 113 data-phase bits, 147 in all
- 12 bytes: 5 + 96 + (29 - 4) + 4 + 17 + 6 = 153, 187 in all
- 32 bytes: 5 + 256 + (69 - 4) + 4 + 21 + 7 = 358, 392 in all
- 64 bytes: 5 + 512 + (133 - 4) + 4 + 21 + 7 = 678, 712 in all
- extended 8 bytes: 36 header bits + 8 stuff + 13 = 57; 5 + 64 + (26 - 8) + 4 + 17 + 6 = 114
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _can_dbcs import FD_DBC, without_data_bitrate, write
from hypothesis import given
from hypothesis import strategies as st

from flowrt import cli
from flowrt.analysis.can import CanMessageTiming, analyse_bus
from flowrt.analysis.can_frames import fd_frame_bits, fd_payload_length, frame_bits

pytestmark = pytest.mark.timeout(30)


@pytest.mark.parametrize(
    ("n", "extended", "arbitration", "data", "crc"),
    [
        (8, False, 34, 113, 17),
        (12, False, 34, 153, 17),
        (32, False, 34, 358, 21),
        (64, False, 34, 678, 21),
        (8, True, 57, 114, 17),
    ],
)
@pytest.mark.parametrize("brs", [True, False])
def test_fd_frame_bits_hand_computed(
    n: int, extended: bool, arbitration: int, data: int, crc: int, brs: bool
) -> None:
    f = fd_frame_bits(n, extended, brs)
    assert (f.arbitration, f.data, f.crc_bits, f.payload) == (arbitration, data, crc, n)
    assert f.total == arbitration + data
    if brs:  # 500 kbit/s arbitration, 2 Mbit/s data
        assert f.seconds(500_000, 2_000_000) == pytest.approx(arbitration / 5e5 + data / 2e6)
    else:  # every bit at the nominal rate, whatever the data rate
        assert f.seconds(500_000, 2_000_000) == pytest.approx((arbitration + data) / 5e5)


def test_brs_without_data_bitrate_is_refused() -> None:
    with pytest.raises(ValueError, match="data bit rate"):
        fd_frame_bits(64).seconds(500_000, None)


@pytest.mark.parametrize(("n", "length"), [(0, 0), (8, 8), (9, 12), (13, 16), (33, 48), (64, 64)])
def test_fd_payload_lengths(n: int, length: int) -> None:
    assert fd_payload_length(n) == length


def test_more_than_64_bytes_and_classic_over_8_are_refused() -> None:
    with pytest.raises(ValueError, match=r"0\.\.64"):
        fd_payload_length(65)
    with pytest.raises(ValueError, match="CAN FD"):
        frame_bits(64)


@given(st.integers(0, 64), st.booleans())
def test_fd_frame_never_shorter_than_its_bits_and_brs_never_slower(n: int, ext: bool) -> None:
    f = fd_frame_bits(n, ext)
    assert f.total >= 8 * fd_payload_length(n) + 5
    assert f.seconds(500_000, 2_000_000) <= fd_frame_bits(n, ext, brs=False).seconds(500_000, None)


def test_fd_8_bytes_is_not_analysed_as_classic() -> None:
    fd = CanMessageTiming("F", 1, 8, 10.0, fd=True, brs=False)
    classic = CanMessageTiming("C", 2, 8, 10.0)
    r = {m.name: m for m in analyse_bus([fd, classic], 500_000).messages}
    assert r["F"].frame_bits == 147
    assert r["C"].frame_bits == 135
    assert r["F"].c_ms == pytest.approx(147 / 500)


def test_analyse_fd_dbc_uses_its_data_bitrate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, FD_DBC)
    assert cli.main(["can", "analyse", path, "--bitrate", "500k", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["data_bitrate"] == 2_000_000  # BaudrateCANFD
    by = {m["name"]: m for m in doc["messages"]}
    assert (by["Fd64"]["arbitration_bits"], by["Fd64"]["data_bits"]) == (34, 678)
    assert by["Fd64"]["c_ms"] == pytest.approx(34 / 500 + 678 / 2000)
    assert by["Fd12"]["frame_bits"] == 187
    assert by["Fd8NoBrs"]["brs"] is False  # CANFD_BRS 0: all at 500 kbit/s
    assert by["Fd8NoBrs"]["c_ms"] == pytest.approx(147 / 500)
    assert by["Classic"]["frame_bits"] == 135
    assert not by["Classic"]["fd"]
    # --data-bitrate overrides the attribute
    assert cli.main(["can", "analyse", path, "--data-bitrate", "4M", "--json"]) == 0
    by = {m["name"]: m for m in json.loads(capsys.readouterr().out)["messages"]}
    assert by["Fd64"]["c_ms"] == pytest.approx(34 / 500 + 678 / 4000)


def test_fd_without_data_bitrate_is_one_named_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "400")  # one line as the program writes it, however long
    path = write(tmp_path, without_data_bitrate(FD_DBC))
    assert cli.main(["can", "analyse", path]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if "no data bit rate" in line]
    assert len(lines) == 1
    assert "Fd64" in lines[0]
    assert "Fd12" in lines[0]
    assert "--data-bitrate" in lines[0]
    assert "Fd8NoBrs" not in lines[0]  # no BRS: needs no data rate
    assert cli.main(["can", "analyse", path, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    left = {m["name"]: m for m in doc["not_analysed"]}
    assert set(left) == {"Fd64", "Fd12", "Event"}
    # still interference for the others, at the no-BRS length (an upper bound)
    classic = next(m for m in doc["messages"] if m["name"] == "Classic")
    assert classic["wcrt_ms"] > (712 + 187) / 500


def test_data_bitrate_below_nominal_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write(tmp_path, FD_DBC)
    assert cli.main(["can", "analyse", path, "--bitrate", "1M", "--data-bitrate", "500k"]) == 2
    err = capsys.readouterr().err
    assert "below" in err
    assert len(err.strip().splitlines()) == 1
