#!/usr/bin/env python3
"""Regenerate src/drvs/v1 from protos/drvs/v1: the one way generated code is made.

Usage: python scripts/gen_protos.py [--out DIR]   (DIR defaults to src; tests pass a temp dir
and compare, so committed code that drifts from the .proto files fails the suite).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROTO_DIR = ROOT / "protos" / "drvs" / "v1"


def generate(out: Path) -> list[Path]:
    import grpc_tools
    from grpc_tools import protoc

    package_dir = out / "drvs" / "v1"
    package_dir.mkdir(parents=True, exist_ok=True)
    for stale in package_dir.glob("*_pb2*"):
        stale.unlink()
    protos = sorted(PROTO_DIR.glob("*.proto"))
    well_known = Path(grpc_tools.__file__).parent / "_proto"
    args = [
        "grpc_tools.protoc",
        f"-Idrvs/v1={PROTO_DIR}",
        f"-I{well_known}",
        f"--python_out={out}",
        f"--pyi_out={out}",
        f"--grpc_python_out={out}",
        *(str(p) for p in protos),
    ]
    if protoc.main(args) != 0:
        raise SystemExit("protoc failed")
    init = package_dir / "__init__.py"
    init.write_text('"""Generated from protos/drvs/v1 by scripts/gen_protos.py; do not edit."""\n')
    return sorted(package_dir.iterdir())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "src")
    args = parser.parse_args()
    for path in generate(args.out):
        print(path.relative_to(args.out))


if __name__ == "__main__":
    sys.exit(main())
