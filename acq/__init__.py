"""Acquisition: scan plans, the tag stream -> pixel assignment, recording, replay, file readers, CLI."""
