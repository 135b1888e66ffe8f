"""Generated from proto/matopt/v1 by proto/generate.py. Do not edit."""
