"""The CLI: one module per command group; each parses, calls the library once, renders."""
