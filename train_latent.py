"""Train the latent (autodecoder) model over a scan collection: not yet implemented."""
import sys


def main(argv=None):
    print("train_latent.py: not yet implemented (see the latent-training issue)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
