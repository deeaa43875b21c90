"""ANSI/NIST-ITL 1-2011 transactions of one print (traditional encoding), by ``nistitl``.

Records, in this order (IDC 1 ties the image and its minutiae together):

- Type-1 transaction information: 1.002 VER ``0500`` (the 2011 edition), 1.003 CNT (the
  record list, written by nistitl), 1.004 TOT, 1.005 DAT, 1.007 DAI, 1.008 ORI, 1.009 TCN,
  1.011 NSR and 1.012 NTR ``19.69`` (500 ppi in pixels per millimetre);
- Type-14 variable-resolution fingerprint image: 14.003 IMP, 14.004 SRC (= ORI), 14.005 FCD,
  14.006 HLL and 14.007 VLL (pixels), 14.008 SLC ``1`` (pixels per inch), 14.009 THPS and
  14.010 TVPS ``500``, 14.011 CGA ``WSQ20``, 14.012 BPX ``8``, 14.013 FGP, 14.999 the WSQ
  file (``records.wsq_image``);
- Type-9 minutiae, only when there are minutiae: 9.003 IMP, 9.004 FMT ``U`` (not the legacy
  9.005-9.012 layout) and the INCITS 378 / ISO 19794-2 block of Table 28: 9.126 CBI
  ``27^513`` (CBEFF owner INCITS M1, ANSI 378 minutiae without ridge counts), 9.127 CEI
  ``NONE^0``, 9.128 HLL, 9.129 VLL, 9.130 SLC ``1``, 9.131 THPS, 9.132 TVPS, 9.133 FVW
  ``0``, 9.134 FGP, 9.135 FQD (the print's NFIQ 2, 0 when it has none), 9.136 NOM, 9.137
  FMD: one subfield a minutia, index ^ x ^ y (pixels, origin top-left) ^ angle (units of 2 degrees,
  counter-clockwise from +x) ^ type (1 ridge ending, 2 bifurcation) ^ quality (1-100).

IMP ``1`` "live-scan rolled": the print is a rolled-equivalent of a live capture.
"""

from __future__ import annotations

import datetime

import numpy as np

from fingerps_recon.errors import RecordError
from fingerps_recon.records.print_minutiae import PrintMinutiae
from fingerps_recon.records.wsq_image import WSQ_PPI

#: 500 ppi in pixels per millimetre, as 1.011 NSR and 1.012 NTR state it.
PPMM_500PPI = "19.69"
LIVE_SCAN_ROLLED = 1
#: ASCII fields hold printable characters; the separators FS GS RS US are below 0x20.
_PRINTABLE = frozenset(range(0x20, 0x7F))


def ansi_nist_transaction(wsq: bytes, width: int, height: int,
                          minutiae: PrintMinutiae | None, *, originating_agency: str,
                          transaction_control: str, transaction_type: str = "FPS",
                          destination_agency: str = "000", finger_position: int = 0,
                          date: datetime.date | None = None) -> bytes:
    """The ANSI/NIST-ITL 1-2011 transaction of one print (module docstring).

    ``wsq`` is the print's WSQ file (``width`` x ``height`` px, 500 ppi); ``minutiae`` its
    minutiae, or None (or none found) for no Type-9 record. ``transaction_control`` (1.009
    TCN) names the transaction: give one of your own (a session and burst, say), never a
    person's data.

    Raises
    ------
    RecordError
        When nistitl is missing, or a text field holds characters the standard's ASCII
        fields cannot (the reason names the field).
    """
    try:
        import nistitl
    except ImportError as exc:
        raise RecordError(f"nistitl is not installed ({exc}): pip install nistitl") from exc
    texts = {"1.004 TOT": transaction_type, "1.007 DAI": destination_agency,
             "1.008 ORI": originating_agency, "1.009 TCN": transaction_control}
    for name, text in texts.items():
        if not text or not set(text.encode("latin-1", "replace")) <= _PRINTABLE:
            raise RecordError(f"{name} {text!r}: give a non-empty printable ASCII text")
    day = (date or datetime.date.today()).strftime("%Y%m%d")

    msg = nistitl.Message()
    r1 = msg[0]
    for tag, value in ((2, "0500"), (4, transaction_type), (5, day), (7, destination_agency),
                       (8, originating_agency), (9, transaction_control),
                       (11, PPMM_500PPI), (12, PPMM_500PPI)):
        setattr(r1, f"_{tag}", value)

    r14 = nistitl.AsciiRecord(14)  # with 14.001 LEN and 14.002 IDC
    r14.IDC = 1
    for tag, value in ((3, LIVE_SCAN_ROLLED), (4, originating_agency), (5, day),
                       (6, width), (7, height), (8, 1), (9, WSQ_PPI), (10, WSQ_PPI),
                       (11, "WSQ20"), (12, 8), (13, finger_position)):
        r14 += nistitl.Field(14, tag, str(value))
    r14 += nistitl.BinaryField(14, 999, bytes(wsq))
    msg += r14

    if minutiae is not None and len(minutiae):
        r9 = nistitl.AsciiRecord(9)
        r9.IDC = 1
        for tag, value in ((3, LIVE_SCAN_ROLLED), (4, "U"), (128, width),
                           (129, height), (130, 1), (131, WSQ_PPI), (132, WSQ_PPI), (133, 0),
                           (134, finger_position), (135, int(np.clip(minutiae.nfiq2 or 0, 0, 100))),
                           (136, len(minutiae))):
            r9 += nistitl.Field(9, tag, str(value))
        r9 += _items_field(nistitl, 9, 126, [("27", "513")])
        r9 += _items_field(nistitl, 9, 127, [("NONE", "0")])
        angle = np.rint(minutiae.angle_deg / 2.0).astype(np.int64) % 180
        rows = zip(range(1, len(minutiae) + 1), minutiae.x_px, minutiae.y_px, angle,
                   minutiae.kind, minutiae.quality, strict=True)
        r9 += _items_field(nistitl, 9, 137, [tuple(str(int(v)) for v in row) for row in rows])
        msg += r9
    return bytes(msg.NIST)


def _items_field(nistitl, record: int, tag: int, subfields: list[tuple[str, ...]]):
    """A field of ``subfields``, each of information items (``a^b^c`` in the standard)."""
    field = nistitl.Field(record, tag)
    for items in subfields:
        sub = nistitl.SubField()
        sub.add_values(*items)
        field.add_subfields(sub)
    return field
