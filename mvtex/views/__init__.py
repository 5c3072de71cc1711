"""Novel views between array cameras and stereo previews (`mvtex views`, `mvtex preview`).
"""
