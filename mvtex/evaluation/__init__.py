"""Evaluation (`mvtex eval`): the per-pixel uv error and the material error.
"""
