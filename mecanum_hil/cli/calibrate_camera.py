"""``mecanum-hil calibrate-camera``: intrinsics and lens distortion from a ChArUco board."""


import json
from pathlib import Path
from typing import Annotated

import typer

from ._options import JsonOpt, refuse_overwriting


def command(
    source: Annotated[Path, typer.Argument(
        help="A video of the board, a folder of images, or one image.",
        metavar="VIDEO_OR_IMAGES")],
    board: Annotated[str, typer.Option(
        "--board", help="charuco:COLSxROWS:SQUARE_M:MARKER_M[:DICTIONARY], e.g. "
        "charuco:7x5:0.04:0.03 (dictionary default DICT_5X5_100; 3..100 squares a side and "
        "at most as many markers, COLS*ROWS/2, as the dictionary has).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="camera.toml to write.")],
    max_views: Annotated[int, typer.Option(
        "--max-views", min=5, help="Frames of a video used, spread over it (at most 500).")
    ] = 60,
    as_json: JsonOpt = False,
) -> None:
    """Calibrate a camera (OpenCV's ChArUco calibration); refuses views that leave part of the
    image without board corners."""
    from ..errors import VideoError
    from ..vision.calibrate import MAX_VIEWS, calibrate, parse_board, read_views
    from ..vision.camera import save_camera

    spec = parse_board(board)
    if max_views > MAX_VIEWS:
        raise VideoError(f"--max-views must be within 5..{MAX_VIEWS}, got {max_views}")
    inputs = ([(f, "an image of the board") for f in sorted(source.iterdir()) if f.is_file()]
              if source.is_dir() else [(source, "the board's video or image")])
    refuse_overwriting(inputs, [(out, "--out")])
    views = read_views(source, max_views)
    result = calibrate(views, spec, str(source))
    cam = result.camera
    save_camera(cam, out, f"mecanum-hil calibrate-camera {source} --board {board}",
                {"views": result.views_used})
    summary = {"out": str(out), "rms_px": round(float(cam.rms_px or 0.0), 4),
               "views": len(views), "views_used": result.views_used, "corners": result.corners,
               "size_px": [cam.width_px, cam.height_px], "fx_px": cam.fx_px, "fy_px": cam.fy_px,
               "cx_px": cam.cx_px, "cy_px": cam.cy_px, "distortion": list(cam.distortion)}
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
        return
    typer.echo(f"RMS reprojection error {summary['rms_px']:.3f} px over {result.corners} corners "
               f"in {result.views_used} of {len(views)} views; fx {cam.fx_px:.1f} px, "
               f"fy {cam.fy_px:.1f} px -> {out}")
