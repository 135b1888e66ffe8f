"""Resource names and pages, as every list and every name of the API takes them."""

from __future__ import annotations

import base64

from ..errors import InvalidArgument

DEFAULT_PAGE, MAX_PAGE = 50, 1000


def resource(prefix: str, name: str) -> str:
    """Accepts 'jobs/abc' or 'abc'."""
    if not name:
        raise InvalidArgument(f"name is empty: expected '{prefix}/<id>'")
    return name if name.startswith(prefix + "/") else f"{prefix}/{name}"


def page(token: str, size: int, default: int = DEFAULT_PAGE, most: int = MAX_PAGE
         ) -> tuple[int, int]:
    """(offset, limit) of a page. Tokens are opaque to clients (an offset in base64 behind a
    tag), so that the daemon may change what they hold without breaking anyone."""
    if size < 0:
        raise InvalidArgument(f"page_size must be >= 0, got {size}")
    offset = 0
    if token:
        try:
            tag, _, digits = base64.urlsafe_b64decode(token.encode("ascii")).decode().partition(":")
            offset = int(digits) if tag == "o" and digits.isdigit() and len(digits) <= 18 else -1
        except (ValueError, UnicodeError):
            offset = -1
        if offset < 0:
            raise InvalidArgument(f"invalid page_token '{token}': pass the next_page_token of "
                                  "the previous page unchanged, or nothing for the first")
    return offset, min(size or default, most)


def next_token(offset: int, limit: int, got: int) -> str:
    if got < limit:
        return ""
    return base64.urlsafe_b64encode(f"o:{offset + limit}".encode()).decode()
