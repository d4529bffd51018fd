"""Generate the Python stubs from proto/ (`make proto`).

    python -m deepcontact.protogen            # write deepcontact/v1/*_pb2*.py
    python -m deepcontact.protogen --check    # exit 1 if they are stale
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROTO = Path("deepcontact/v1/warmstart.proto")
OUTPUTS = ("deepcontact/v1/warmstart_pb2.py", "deepcontact/v1/warmstart_pb2_grpc.py")


def generate(out_dir: Path) -> list[Path]:
    """Run protoc (from grpcio-tools) on the .proto into out_dir; return the files."""
    from grpc_tools import protoc

    out_dir.mkdir(parents=True, exist_ok=True)
    args = ["protoc", f"-I{ROOT / 'proto'}", f"--python_out={out_dir}", f"--grpc_python_out={out_dir}",
            str(ROOT / "proto" / PROTO)]
    if protoc.main(args) != 0:
        raise RuntimeError(f"protoc failed on proto/{PROTO}")
    return [out_dir / o for o in OUTPUTS]


def stale() -> list[str]:
    """Committed stubs that differ from freshly generated ones."""
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp))
        return [o for o, f in zip(OUTPUTS, fresh) if (ROOT / o).read_bytes() != f.read_bytes()]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--check", action="store_true", help="only check; exit 1 when the stubs are stale")
    args = parser.parse_args()
    if args.check:
        bad = stale()
        for o in bad:
            print(f"{o} is stale: run `make proto`", file=sys.stderr)
        return 1 if bad else 0
    generate(ROOT)
    print("regenerated " + ", ".join(OUTPUTS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
