"""A Rerun layout (blueprint) for fmfusion's live view: a wide 3D view with the instance boxes labelled, the
camera image with its detections beside it, the side panels folded.

    python examples/rerun_layout.py fmfusion.rbl        # needs the viewer extra: pip install -e ".[viewer]"
    rerun OUT/fusion.rrd fmfusion.rbl                   # a recording made with fmfusion run --viewer-save

The entity paths are those `fmfusion_jax.viz.live` logs (`/world/instances`, `/world/camera/image`).
The viewer hides the boxes' labels by default once a map holds a few dozen instances; this layout shows them.
The fixed eye suits the generated demo room (metres, z up); drop `eye_controls` for the viewer's own.
"""

from __future__ import annotations

import argparse

import rerun as rr
import rerun.blueprint as rrb


def layout() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(
                name="world (3D)",
                origin="/world",
                contents=["+ /world/**", "- /world/camera/image/depth"],
                overrides={"world/instances": rr.Boxes3D.from_fields(show_labels=True)},
                eye_controls=rrb.EyeControls3D(position=[-1.3, -2.6, 4.6], look_target=[2.5, 2.0, 0.5], eye_up=[0, 0, 1]),
            ),
            rrb.Spatial2DView(
                name="camera image", origin="/world/camera/image", contents=["+ $origin/**", "- /world/camera/image/depth"]
            ),
            column_shares=[2.2, 1],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", help="the blueprint file to write (.rbl)")
    args = parser.parse_args()
    layout().save("fmfusion", args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
