"""Every exchange record of one 500 ppi print, with the reason for each one not made.

- ``fingerprint.wsq``: the WSQ image (``wsq_image``, NBIS's codec at 0.75 bpp);
- ``fingerprint.fmr``: the ISO/IEC 19794-2:2005 minutiae record (``iso_minutiae_record``);
- ``fingerprint.an2``: the ANSI/NIST-ITL 1-2011 transaction, Type-1 + Type-14 (the WSQ
  image) + Type-9 (the minutiae) (``ansi_nist_transaction``).

A record that cannot be made is left out, never written empty: no WSQ image (the codec does
not give the print back) means no transaction either; no minutiae (NBIS finds none) means no
ISO record and a transaction without Type-9.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fingerps_recon.errors import RecordError, WsqError
from fingerps_recon.records.ansi_nist_transaction import ansi_nist_transaction
from fingerps_recon.records.iso_minutiae_record import iso_minutiae_record
from fingerps_recon.records.print_minutiae import PrintMinutiae, find_minutiae
from fingerps_recon.records.wsq_image import WSQ_BITRATE, encode_wsq

#: File name of each record, beside ``fingerprint.png``.
FILE_NAMES = {"wsq": "fingerprint.wsq", "iso_template": "fingerprint.fmr",
              "transaction": "fingerprint.an2"}


@dataclass(frozen=True)
class PrintRecords:
    """The records of one print (None where not made: ``reasons`` says why) and its minutiae
    (None when NBIS could not run)."""

    wsq: bytes | None
    iso_template: bytes | None
    transaction: bytes | None
    minutiae: PrintMinutiae | None
    reasons: dict[str, str] = field(default_factory=dict)

    @property
    def nfiq2(self) -> int | None:
        return None if self.minutiae is None else self.minutiae.nfiq2

    def write(self, folder: Path) -> list[str]:
        """Write the records made into ``folder``; return their file names."""
        written = []
        for name, file_name in FILE_NAMES.items():
            data = getattr(self, name)
            if data is not None:
                (folder / file_name).write_bytes(data)
                written.append(file_name)
        return written

    def report(self) -> dict:
        """What report.json and the Scan result say of the records."""
        made = {"wsq": {"bitrate_bpp": WSQ_BITRATE},
                "iso_template": {"standard": "ISO/IEC 19794-2:2005"},
                "transaction": {"standard": "ANSI/NIST-ITL 1-2011",
                                "records": "1, 14, 9" if self.iso_template else "1, 14"}}
        out: dict = {"nfiq2": self.nfiq2,
                     "minutiae": None if self.minutiae is None else len(self.minutiae)}
        if self.minutiae is not None and self.minutiae.nfiq2_problem:
            out["nfiq2_problem"] = self.minutiae.nfiq2_problem
        for name, file_name in FILE_NAMES.items():
            data = getattr(self, name)
            out[file_name] = ({"made": True, "bytes": len(data), **made[name]}
                              if data is not None else
                              {"made": False, "reason": self.reasons[name]})
        return out


def make_print_records(image: np.ndarray, *, transaction_control: str,
                       originating_agency: str = "FINGERPS",
                       date: datetime.date | None = None,
                       minutiae: PrintMinutiae | None = None) -> PrintRecords:
    """The records of a 500 ppi print (H, W) uint8, ridges dark (module docstring).

    ``transaction_control`` names the ANSI/NIST transaction (1.009 TCN); see
    ``ansi_nist_transaction``. ``minutiae``: the print's, when already found
    (``find_minutiae``); None finds them.
    """
    reasons: dict[str, str] = {}
    try:
        wsq = encode_wsq(image)
    except WsqError as exc:
        wsq = None
        reasons["wsq"] = str(exc)
        reasons["transaction"] = f"no WSQ image for its Type-14 record ({exc})"
    if minutiae is None:
        try:
            minutiae = find_minutiae(image)
        except RecordError as exc:
            reasons["iso_template"] = str(exc)
    iso = None
    if minutiae is not None:
        if len(minutiae):
            iso = iso_minutiae_record(minutiae)
        else:
            reasons["iso_template"] = ("NBIS found no minutiae in the print (NFIQ 2 "
                                       f"{minutiae.nfiq2}): no template written")
    transaction = None
    if wsq is not None:
        transaction = ansi_nist_transaction(
            wsq, image.shape[1], image.shape[0], minutiae if iso is not None else None,
            originating_agency=originating_agency, transaction_control=transaction_control,
            date=date)
    return PrintRecords(wsq, iso, transaction, minutiae, reasons)
