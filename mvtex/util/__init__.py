"""Foundations every stage uses: errors, safe file input and output, fingerprints, parallel maps.
"""
