"""A drillnav client in 20 lines: print the drill axis, over TLS, as the site's display-1."""
import json, sys, zenoh

endpoint, site, name = sys.argv[1:4]  # e.g. tls/navcart.local:7447 /etc/drillnav/site display-1
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')  # through the daemon alone, which checks who may publish what
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("transport/link/tls", json.dumps({
    "root_ca_certificate": f"{site}/ca.pem", "enable_mtls": True,
    "connect_certificate": f"{site}/{name}.pem", "connect_private_key": f"{site}/{name}.key"}))

def on_axis(sample):
    axis = json.loads(sample.payload.to_bytes())
    err = axis["predicted_error"]
    print(f"axis {axis['registration_id']}.{axis.get('sequence')} through {axis['point_mm']} mm along {axis['direction']}"
          f" (±{err['position_mm']:.1f} mm, ±{err['angle_deg']:.1f} deg)", flush=True)

with zenoh.open(conf) as session:
    session.declare_subscriber("drillnav/axis/carm", on_axis)
    input("listening; Enter to stop\n")
