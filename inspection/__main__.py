"""Command line of the inspection package (placeholder until the inspection issue)."""
import sys


def main(argv=None):
    print("inspection: not yet implemented", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
