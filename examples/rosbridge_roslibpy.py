"""DRVS through drvs_gateway's rosbridge endpoint with roslibpy (docs/gateway.md, "rosbridge
endpoint"): host a CallbackCoordinates service, ask DRVS for the objects in a region, print the
outlines. Run: DRVS_TOKEN=... python examples/rosbridge_roslibpy.py"""

import os
import threading

import roslibpy

host, port = os.environ.get('DRVS_ROSBRIDGE', '127.0.0.1:9090').rsplit(':', 1)
headers = {'Authorization': f'Bearer {os.environ["DRVS_TOKEN"]}'} if 'DRVS_TOKEN' in os.environ else None
ros = roslibpy.Ros(host, int(port), headers=headers)
ros.run(timeout=10)
called_back = threading.Event()


def on_callback(request, response):
    for found in request['objects']:
        points = [[round(p['x'], 3), round(p['y'], 3)] for p in found['boundary']['points']]
        print(request['vision_system'], 'sees', found['label'] or 'an object', 'at', points)
    called_back.set()
    return True


callback = roslibpy.Service(ros, '/my_robot/drvs_callback', 'drvs/CallbackCoordinates')
callback.advertise(on_callback)
detect = roslibpy.Service(ros, '/drvs/detect_object_boundary', 'drvs/DetectObjectBoundary')
ask = {
    'algorithm': 'colour:0,0,150,80,80,255',
    'region_of_interest': {'min_x': 0, 'min_y': 0, 'max_x': 4, 'max_y': 4},
    'callback_service': '/my_robot/drvs_callback',
    'request_id': 'roslibpy-1',
}
answer = detect.call(roslibpy.ServiceRequest(ask), timeout=10)
print('status', answer['status'], 'vision systems', answer['vision_systems'])
if not called_back.wait(15):
    raise SystemExit('no callback within 15 s')
callback.unadvertise()
ros.terminate()
