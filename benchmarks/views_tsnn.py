"""Novel views from predicted texcoords: per-camera models for the two stereo cameras, then
`blend` and `reconstruct` between them, against direct texture sliding at each view (with
gt). Prints the same-chart SqrtMSE at the cameras and at the midpoint, as a Markdown table.

    python benchmarks/views_tsnn.py WORKDIR [TOTAL_POSES] [PATH_POSES] [EPOCHS]

Default: a 1,200-pose dataset (960 training poses), the per-camera default model (`gp`;
EPOCHS applies only to the networks) on TS without subdivision, the path measured on the
first 12 test poses.
"""

import json
import sys
from pathlib import Path

from mvtex.data.dataset import load_dataset
from mvtex.data.rig import builtin_rig_file, load_rig
from mvtex.data.texcoords import open_texcoords
from mvtex.sliding.dataset import slide_dataset
from mvtex.sliding.options import SlideOptions
from mvtex.synth.generate import SynthOptions, write_synth
from mvtex.tsnn.predict import predict
from mvtex.tsnn.train import TrainOptions, train_camera
from mvtex.views.cameras import between_weights, view_names
from mvtex.views.measure import measure_views


def main(work: Path, total: int = 1200, path_poses: int = 12, epochs: int = 60) -> dict:
    data = work / f"shirt{total}"
    if not (data / "dataset.json").exists():
        write_synth(data, SynthOptions(num_poses=total))
    ds = load_dataset(data)
    stereo = load_rig(builtin_rig_file("stereo"))
    test = ds.split["test"]
    ts = work / "ts_stereo_s0"
    if not (ts / "texcoords.json").exists():
        slide_dataset(ds, stereo, ts, poses=ds.split["train"] + ds.split["val"] + test, options=SlideOptions(subdiv=0))
    tc = open_texcoords(ts, ds.num_vertices)
    models = []
    for camera in stereo.names:
        model = work / f"tsnn_{camera}"
        if not (model / "config.json").exists():
            train_camera(ds, tc, camera, model, TrainOptions(seed=0, epochs=epochs))
        models.append(model)
    pred = work / "tsnn_test"
    if not (pred / "texcoords.json").exists():
        predict(ds, models, pred, poses=test)
    weights = between_weights("left", "right", 5)
    measured = measure_views(ds, stereo, open_texcoords(pred, ds.num_vertices), weights, view_names(5),
                             poses=test[:path_poses])
    (work / "views_tsnn.json").write_text(json.dumps(measured, indent=1))
    print(f"\nTSNN texcoords, {path_poses} test poses, SqrtMSE e-3 (same-chart):\n")
    print("| method | at the cameras | midpoint |")
    print("|---|---|---|")
    for curve, v in measured["sqrt_mse_same_chart"].items():
        name = {"blend": "TSNN blend", "reconstruct": "TSNN reconstruct"}.get(curve, curve)
        print(f"| {name} | {(v[0] + v[-1]) / 2 * 1e3:.3f} | {v[2] * 1e3:.3f} |")
    return measured


if __name__ == "__main__":
    main(Path(sys.argv[1]), *(int(a) for a in sys.argv[2:]))
