"""Importers: other systems' recordings -> v1 session folders (written through midas_cli.session)."""
