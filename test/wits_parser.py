"""A WITS level 0 reader written for the tests from the framing rules (``&&`` CR LF, lines of a
four-digit code ``RRII`` followed by the value, ``!!`` CR LF), independent of our encoder."""


def parse_wits0(data: bytes) -> list:
    """Records of a WITS0 byte stream: each a dict {(record, item): value text}; raises on a
    malformed frame."""
    text = data.decode("ascii")
    out = []
    for chunk in text.split("&&\r\n")[1:]:
        body, sep, _ = chunk.partition("!!\r\n")
        if not sep:
            raise ValueError("record without its '!!' end")
        rec = {}
        for line in body.split("\r\n"):
            if not line:
                continue
            if len(line) < 4 or not line[:4].isdigit():
                raise ValueError(f"bad WITS0 line {line!r}")
            rec[(int(line[:2]), int(line[2:4]))] = line[4:]
        out.append(rec)
    return out
