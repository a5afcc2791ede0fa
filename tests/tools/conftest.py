"""Tooling tests: Makefile, scripts/ and the manifest. Nothing here imports bpy."""
