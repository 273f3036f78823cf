"""DBC texts for the CAN tests: CAN FD messages (with and without bit-rate switch, a data bit
rate declared), a multiplexed message, an event-driven one, and a strict-refused layout."""

from __future__ import annotations

from pathlib import Path

#: VFrameFormat's values as Vector defines them: 14 is StandardCAN_FD, 15 ExtendedCAN_FD.
_NAMES = ["StandardCAN", "ExtendedCAN", "reserved", "J1939PG", *(["reserved"] * 10)]
_FORMATS = ",".join(f'"{v}"' for v in [*_NAMES, "StandardCAN_FD", "ExtendedCAN_FD"])

FD_DBC = """VERSION ""

NS_ :

BS_:

BU_: PC ECU

BO_ 256 Fd64: 64 ECU
 SG_ Lead : 0|16@1+ (1,0) [0|65535] "" PC
 SG_ Tail : 496|16@1+ (1,0) [0|65535] "" PC

BO_ 257 Fd12: 12 ECU
 SG_ Value : 0|32@1+ (1,0) [0|4294967295] "" PC

BO_ 258 Fd8NoBrs: 8 ECU
 SG_ X : 0|8@1+ (1,0) [0|255] "" PC

BO_ 512 Mux: 8 PC
 SG_ Page M : 0|8@1+ (1,0) [0|3] "" ECU
 SG_ Speed m0 : 8|16@1+ (0.1,0) [0|100] "" ECU
 SG_ Temp m1 : 8|16@1+ (1,-40) [-40|150] "" ECU
 SG_ Flags m1 : 24|8@1+ (1,0) [0|255] "" ECU

BO_ 768 Classic: 8 ECU
 SG_ C : 0|8@1+ (1,0) [0|255] "" PC

BO_ 1024 Event: 2 ECU
 SG_ E : 0|8@1+ (1,0) [0|255] "" PC

BA_DEF_  "BusType" STRING ;
BA_DEF_  "BaudrateCANFD" INT 0 10000000;
BA_DEF_ BO_  "GenMsgCycleTime" INT 0 65535;
BA_DEF_ BO_  "VFrameFormat" ENUM  {formats};
BA_DEF_ BO_  "CANFD_BRS" ENUM  "0","1";
BA_DEF_DEF_  "BusType" "CAN FD";
BA_DEF_DEF_  "BaudrateCANFD" 2000000;
BA_DEF_DEF_  "GenMsgCycleTime" 0;
BA_DEF_DEF_  "VFrameFormat" "StandardCAN";
BA_DEF_DEF_  "CANFD_BRS" "1";
BA_ "BusType" "CAN FD";
BA_ "BaudrateCANFD" 2000000;
BA_ "GenMsgCycleTime" BO_ 256 10;
BA_ "VFrameFormat" BO_ 256 14;
BA_ "GenMsgCycleTime" BO_ 257 10;
BA_ "VFrameFormat" BO_ 257 14;
BA_ "GenMsgCycleTime" BO_ 258 10;
BA_ "VFrameFormat" BO_ 258 14;
BA_ "CANFD_BRS" BO_ 258 0;
BA_ "GenMsgCycleTime" BO_ 512 10;
BA_ "GenMsgCycleTime" BO_ 768 10;
""".replace("{formats}", _FORMATS)

#: Overlapping signals and a signal past the message's end: cantools refuses it strictly.
OVERLAP_DBC = """VERSION ""

NS_ :

BS_:

BU_: PC

BO_ 100 Over: 2 PC
 SG_ A : 0|8@1+ (1,0) [0|255] "" PC
 SG_ B : 4|8@1+ (1,0) [0|255] "" PC
 SG_ C : 12|8@1+ (1,0) [0|255] "" PC

BO_ 101 Fine: 1 PC
 SG_ D : 0|8@1+ (1,0) [0|255] "" PC

BA_DEF_ BO_  "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_  "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 100 10;
BA_ "GenMsgCycleTime" BO_ 101 20;
"""


def write(tmp: Path, text: str, name: str = "bus.dbc") -> str:
    path = tmp / name
    path.write_text(text)
    return str(path)


def without_data_bitrate(text: str) -> str:
    """The FD database without its BaudrateCANFD attribute."""
    return "\n".join(line for line in text.splitlines() if "BaudrateCANFD" not in line) + "\n"


#: The largest production databases of the ``opendbc`` package (the test extra) that cantools
#: loads, by size: a 331-message CAN FD powertrain, a 367-message body bus of extended ids
#: (1675 overlapping signals strict loading refuses), CAN FD ADAS, multiplexed messages.
VEHICLE_DBCS = (
    "ford_lincoln_base_pt.dbc",
    "gm_global_a_lowspeed_1818125.dbc",
    "bmw_e9x_e8x.dbc",
    "cadillac_ct6_object.dbc",
    "generator/hyundai/hyundai_canfd.dbc",
    "vw_mqb.dbc",
    "hyundai_2015_ccan.dbc",
)


def opendbc(name: str) -> str:
    """The path of one of opendbc's DBC files (installed with the test extra)."""
    from importlib.metadata import version

    import opendbc as package

    path = Path(package.DBC_PATH) / name
    if not path.is_file():
        raise FileNotFoundError(f"opendbc {version('opendbc')} has no {name}")
    return str(path)
