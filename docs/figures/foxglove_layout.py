"""Write docs/foxglove_layout.json: a Foxglove layout that opens a drillnav recording (or the live bridge) as a navigation view.

Run: .venv/bin/python docs/figures/foxglove_layout.py
Built with foxglove-sdk's typed layout classes (foxglove.layouts), so the file follows Foxglove's own
layout schema; the topic names come from drillnav.schemas.topics, so it cannot drift from the wire.
"""

from pathlib import Path

import foxglove.layouts as fl

from drillnav.schemas.foxglove_scene import FRAME_CARM, FRAME_DRILL_CAMERA
from drillnav.schemas.topics import key

OUT = Path(__file__).resolve().parents[1] / "foxglove_layout.json"
PREFIX = "drillnav"
VIEWS = ("inlet", "outlet")  # the twin's view names; edit for other set-ups


def fluoro_panel(view: str) -> fl.ImagePanel:
    """A fluoroscopy view with the scene projected through its own P, and the axis/markers annotations."""
    return fl.ImagePanel(title=f"fluoroscopy {view}", config=fl.ImageConfig(
        topics={key(PREFIX, "scene_entities"): fl.BaseRendererSceneUpdateTopicSettings(visible=True)},
        image_mode=fl.ImageModeConfig(
            image_topic=key(PREFIX, "fluoro_image", view), image_schema_name="foxglove.CompressedImage",
            calibration_topic=key(PREFIX, "scene_calibration", view),
            annotations={key(PREFIX, "scene_annotations", view): fl.ImageAnnotationSettings(visible=True)})))


def main() -> None:
    three_d = fl.ThreeDeePanel(title="navigation (C-arm frame)", config=fl.ThreeDeeConfig(
        fixed_frame=FRAME_CARM, follow_tf=FRAME_CARM,
        topics={key(PREFIX, "scene_entities"): fl.BaseRendererSceneUpdateTopicSettings(visible=True)}))
    camera = fl.ImagePanel(title="drill camera", config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
        image_topic=key(PREFIX, "camera_image"), image_schema_name="foxglove.CompressedImage",
        calibration_topic=key(PREFIX, "scene_calibration", FRAME_DRILL_CAMERA))))
    axis = f'"{key(PREFIX, "axis_carm")}"'  # topic names without a leading slash are quoted in message paths
    plot = fl.PlotPanel(title="predicted axis error", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"{axis}.predicted_error.angle_deg", label="angle (deg)", enabled=True),
        fl.PlotSeries(value=f"{axis}.predicted_error.position_mm", label="position (mm)", enabled=True)]))
    log = fl.LogPanel(config=fl.LogConfig())
    layout = fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=2, content=three_d),
            fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="row", items=[fl.SplitItem(proportion=1, content=plot), fl.SplitItem(proportion=1, content=log)]))])),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            *(fl.SplitItem(proportion=1, content=fluoro_panel(v)) for v in VIEWS),
            fl.SplitItem(proportion=1, content=camera)])),
    ]))
    OUT.write_text(layout.to_json() + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
