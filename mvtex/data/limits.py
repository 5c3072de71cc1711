"""Limits that every reader and writer of mvtex's files shares (one constant each)."""

MAX_SUBDIV = 3
"""Most levels of midpoint subdivision of an inferred mesh: 64x its triangles at 3. Sliding,
texcoord sets and models all take 0..MAX_SUBDIV."""
