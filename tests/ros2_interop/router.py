"""The ROS 2 router of tests/test_ros2_interop.py: a Zenoh router opened with rmw_zenoh's own router
configuration (DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5, as `ros2 run rmw_zenoh_cpp rmw_zenohd` opens
it), listening on loopback at the port given instead of 7447. Runs in the interop environment, on
the Zenoh that rmw_zenoh pins. Prints `ready` once listening; leaves when its stdin closes.

    python router.py CONFIG PORT
"""

import sys

import zenoh

config_path, port = sys.argv[1], int(sys.argv[2])
config = zenoh.Config.from_file(config_path)
config.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{port}"]')
with zenoh.open(config):
    print("ready", flush=True)
    sys.stdin.read()
