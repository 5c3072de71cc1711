"""AR preview: a stereo pair of a built-in pose, seen from between the two cameras of a rig.

    python examples/ar_preview.py [OUT] [NUM_POSES]

Synthesizes a small dataset of the built-in shirt, slides texture coordinates for the
`stereo` rig on one test pose, and renders what a headset between the two cameras shows:
OUT/preview/stereo.png (left eye | right eye), anaglyph.png (red-cyan), comparison.png
and preview.json (SSIM and PSNR of each eye against the ground-truth cloth).
"""

import sys
from pathlib import Path

import mvtex


def main(out: Path, num_poses: int = 20) -> "mvtex.views.preview.Preview":
    mvtex.write_synth(out / "shirt", mvtex.SynthOptions(num_poses=num_poses))       # mvtex synth
    dataset = mvtex.load_dataset(out / "shirt")
    rig = mvtex.load_rig("stereo")
    pose = dataset.split["test"][0]
    mvtex.slide_dataset(dataset, rig, out / "ts", poses=[pose], options=mvtex.SlideOptions(subdiv=1),
                        progress=False)                                              # mvtex slide
    preview = mvtex.stereo_preview(dataset, rig, mvtex.open_texcoords(out / "ts"), pose, out / "preview",
                                   options=mvtex.PreviewOptions(ipd=0.064), progress=False)  # mvtex preview
    for eye, scores in preview.eyes.items():
        inferred, sliding = scores.ssim
        print(f"{eye} eye: SSIM with the predictor's texcoords {inferred:.3f}, with texture sliding {sliding:.3f}")
    print(f"open {out / 'preview' / 'stereo.png'} or {out / 'preview' / 'anaglyph.png'}")
    return preview


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "ar-preview-out"), int(sys.argv[2]) if len(sys.argv) > 2 else 20)
