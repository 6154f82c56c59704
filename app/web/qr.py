"""Links a tablet opens, as inline SVG QR codes (no script, no image request): tablet and kiosk
links, shown on the participant's page, the stations page and the console.

A link is made from the address the staff member's browser used. When that is this computer's
own (127.0.0.1, localhost), a tablet scanning the code would reach itself, not trustlab: the
link says so rather than hand out a code that cannot work."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import qrcode
import qrcode.image.svg
from fastapi import Request

LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})


@lru_cache(maxsize=64)
def qr_svg(url: str) -> str:
    """An SVG QR code of ``url`` (error correction M: survives a scratched screen). Kept per
    URL: the console redraws on every live event while it waits for the tablet, and a link
    changes only when it is reissued."""
    code = qrcode.QRCode(error_correction=qrcode.constants.ERROR_CORRECT_M, box_size=10, border=2)
    code.add_data(url)
    image = code.make_image(image_factory=qrcode.image.svg.SvgPathImage)
    svg: str = image.to_string(encoding="unicode")
    return svg


@dataclass(frozen=True)
class TabletLink:
    """A link for a tablet: its URL, its QR code, and whether it names this computer itself."""

    url: str
    qr: str
    loopback: bool


def tablet_link(request: Request, path: str) -> TabletLink:
    """The link to ``path`` on the address this request came to, with its QR code."""
    url = f"{str(request.base_url).rstrip('/')}{path}"
    host = (request.url.hostname or "").strip("[]").lower()
    loopback = host in LOOPBACK_HOSTS or host.startswith("127.")
    return TabletLink(url=url, qr=qr_svg(url), loopback=loopback)
