"""A plain Zenoh publisher (eclipse-zenoh only, no flowrt) feeding a flowrt import declared
with ``format: json``: no header, the payload is the value.

    python docs/examples/zenoh_plain_pub.py tcp/127.0.0.1:7460 demo/cmd 20
"""

import json
import sys
import time

import zenoh

endpoint, key, count = sys.argv[1], sys.argv[2], int(sys.argv[3])
conf = zenoh.Config()
conf.insert_json5("mode", '"client"')
conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
conf.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(conf) as session:
    pub = session.declare_publisher(key, encoding=zenoh.Encoding.APPLICATION_JSON)
    for i in range(count):
        pub.put(json.dumps({"vx": 0.1 * i, "w": 0.0}))
        time.sleep(0.05)
