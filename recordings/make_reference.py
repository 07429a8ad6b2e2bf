"""Make recordings/twin-seed21.mcap: a short twin session that tests replay through the registration node.

Two fluoroscopy shots (inlet, outlet), then 20 drill-camera frames along a freehand path, each followed by
its truth (drillnav/twin/truth). Run: .venv/bin/python recordings/make_reference.py
"""

import time
from pathlib import Path

from drillnav.drivers.sim.devices import TwinDrillCamera
from drillnav.drivers.sim.scene import TRUE_DRILL_AXIS_CAMERA, make_scene
from drillnav.schemas import messages as msg
from drillnav.schemas.geometry_json import axis_to_json, transform_to_json
from drillnav.schemas.topics import key
from drillnav.service.bus import open_session
from drillnav.service.recorder import Recorder

OUT = Path(__file__).resolve().parent
SEED = 21


def main() -> None:
    scene = make_scene(seed=SEED)
    camera = TwinDrillCamera(scene=scene, fps=15, loop_frames=20, seed=SEED)
    for old in OUT.glob("twin-seed21*.mcap"):
        old.unlink()
    ep = "tcp/127.0.0.1:17399"
    with open_session(listen=[ep]) as pub, open_session(connect=[ep]) as rec_session:
        rec = Recorder(session=rec_session, prefix="drillnav", folder=OUT, name="twin-seed21")
        time.sleep(0.5)
        for name in scene.views:
            pub.put(key("drillnav", "fluoro_shot"), msg.FluoroShot.build(scene.fluoro_log[name], scene.views[name], stamp_ns=time.time_ns(), view_name=name).to_bytes())
        time.sleep(1.5)  # the node registers before the camera starts
        with camera as cam:
            for _ in range(20):
                frame = cam.read()
                pub.put(key("drillnav", "camera_image"), msg.compressed_image(frame.image, stamp_ns=frame.stamp_ns, frame_id="drill_camera", quality=85))
                pub.put(key("drillnav", "twin_truth"), msg.encode_json({
                    "frame_stamp_ns": frame.stamp_ns, "carm_from_drill": transform_to_json(frame.carm_from_drill),
                    "drill_axis_carm": axis_to_json(TRUE_DRILL_AXIS_CAMERA.transformed(frame.carm_from_drill)),
                }))
        time.sleep(0.5)
        (path,) = rec.close()
    final = OUT / "twin-seed21.mcap"
    path.rename(final)
    print(f"wrote {final} ({final.stat().st_size / 1e6:.1f} MB)")


if __name__ == "__main__":
    main()
