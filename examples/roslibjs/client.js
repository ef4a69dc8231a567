// DRVS through drvs_gateway's rosbridge endpoint with roslibjs (docs/gateway.md, "rosbridge endpoint"):
// host a CallbackCoordinates service, ask DRVS for the objects in a region, print the outlines.
// Run: cd examples/roslibjs && npm ci && DRVS_TOKEN=... node client.js
const ROSLIB = require('roslib');

const ros = new ROSLIB.Ros({url: process.env.DRVS_ROSBRIDGE || 'ws://127.0.0.1:9090'});
ros.on('error', (error) => { console.error('rosbridge:', error.message || error); process.exit(1); });
if (process.env.DRVS_TOKEN) ros.authenticate(process.env.DRVS_TOKEN);  // the first message sent
const giveUp = setTimeout(() => { console.error('no callback within 15 s'); process.exit(1); }, 15000);

const callback = new ROSLIB.Service({ros, name: '/my_robot/drvs_callback', serviceType: 'drvs/CallbackCoordinates'});
callback.advertise((request, response) => {
  for (const found of request.objects) {
    const points = found.boundary.points.map((p) => [+p.x.toFixed(3), +p.y.toFixed(3)]);
    console.log(request.vision_system, 'sees', found.label || 'an object', 'at', JSON.stringify(points));
  }
  clearTimeout(giveUp);
  setTimeout(() => ros.close(), 100);  // after the response has gone out
  return true;
});

const detect = new ROSLIB.Service({ros, name: '/drvs/detect_object_boundary', serviceType: 'drvs/DetectObjectBoundary'});
detect.callService({
  algorithm: 'colour:0,0,150,80,80,255',
  region_of_interest: {min_x: 0, min_y: 0, max_x: 4, max_y: 4},
  callback_service: '/my_robot/drvs_callback',
  request_id: 'roslibjs-1',
}, (answer) => console.log('status', answer.status, 'vision systems', answer.vision_systems),
(error) => { console.error('refused:', error); process.exit(1); });
