"""Calibrating camera arrays from ChArUco boards, and rig tools.
"""
