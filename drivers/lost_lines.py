"""Lines (logs, sentences) lost to byte errors on a line-based stream, counted by their bytes:
the one rule of the CSV/NMEA decoder (:class:`rigctl.drivers.frame_decl.CsvStream`) and the
NovAtel mark log reader (:class:`rigctl.drivers.novatel.MarkLogReader`)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class LostLines:
    """Lines lost in the gap between good lines: ``round(g / r)``, ``g`` the bytes since the last
    good line that belong to no good line, ``r`` the last good line's length in bytes (its line
    end included; before the first, ``nominal``; neither known: one line). A damaged line leaves
    all its bytes, whatever the error made of them (a line end, a start character), so it counts
    once however it was cut. Counted as the bytes come and never twice (a gap's count only
    grows): the same whatever the read chunking."""

    nominal: int = 0
    gap: int = 0     # bytes since the end of the last good line
    lost: int = 0    # lines counted lost in this gap
    ref: int = 0     # bytes of the last good line (0: none yet -> nominal)

    def good(self, size: int) -> None:
        """A good line of ``size`` bytes (line end included): the gap ends, it is the reference."""
        self.gap, self.lost, self.ref = 0, 0, size

    def end(self) -> None:
        """The stream ended (a decoder's flush, e.g. when the link is lost): this gap's count is
        final, bytes after it start a new gap (the reference stays)."""
        self.gap, self.lost = 0, 0

    def at_least(self, n: int) -> int:
        """At least ``n`` lines lost in this gap; returns how many more that counts."""
        more = max(0, n - self.lost)
        self.lost += more
        return more

    def garbage(self, size: int, whole: bool = False) -> int:
        """``size`` more bytes in the gap; ``whole``: they are one whole-framed bad line, which
        costs at least ``floor(g / r) + 1`` (itself) for the ``g`` bytes before it. Returns the
        lines newly counted lost."""
        r = self.ref or self.nominal
        self.gap += size
        if not r:  # no length known: one line
            return self.at_least(1)
        more = self.at_least((self.gap - size) // r + 1) if whole else 0
        return more + self.at_least(int(round(self.gap / r)))
