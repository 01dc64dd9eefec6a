"""Regenerate the generated sections of firmware_proto/PROTOCOL.md (test vectors, link budget).

Usage: ``python tools/gen_protocol_vectors.py`` rewrites the file in place;
``python tools/gen_protocol_vectors.py --check`` exits 1 if it is out of date.
"""

from __future__ import annotations

import argparse
import sys

from firmware_proto.budget import render_budget_table
from firmware_proto.vectors import (
    BUDGET_BEGIN,
    BUDGET_END,
    PROTOCOL_MD,
    VECTORS_BEGIN,
    VECTORS_END,
    render_vectors_section,
    replace_section,
)


def main(argv: list[str] | None = None) -> int:
    """Rewrite (or ``--check``) the generated sections of PROTOCOL.md."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check; exit 1 if out of date")
    args = parser.parse_args(argv)
    old = PROTOCOL_MD.read_text(encoding="utf-8")
    new = replace_section(old, VECTORS_BEGIN, VECTORS_END, render_vectors_section())
    new = replace_section(new, BUDGET_BEGIN, BUDGET_END, render_budget_table())
    if args.check:
        if new != old:
            print(f"{PROTOCOL_MD}: generated sections out of date; run tools/gen_protocol_vectors.py")
            return 1
        print(f"{PROTOCOL_MD}: up to date")
        return 0
    if new != old:
        PROTOCOL_MD.write_text(new, encoding="utf-8")
        print(f"{PROTOCOL_MD}: updated")
    else:
        print(f"{PROTOCOL_MD}: unchanged")
    return 0


if __name__ == "__main__":
    sys.exit(main())
