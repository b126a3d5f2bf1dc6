"""Generated from protos/drvs/v1 by scripts/gen_protos.py; do not edit."""
