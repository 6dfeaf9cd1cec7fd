// An independent Sparkplug B codec for tests/sparkplug: Eclipse Tahu JS (npm sparkplug-payload).
// stdin: one JSON request a line; stdout: one JSON answer a line, in order.
//   {"decode": "<base64>"} -> {"payload": Tahu's decodePayload, "raw": the protobufjs message
//                              (which wire field holds each value; Longs as text)}
//   {"encode": {...}}      -> {"b64": encodePayload's bytes, base64}
const spb = require('sparkplug-payload').get('spBv1.0');
const proto = require('sparkplug-payload/lib/sparkplugPayloadProto').org.eclipse.tahu.protobuf;
const long = (k, v) => (v && v.low !== undefined && v.high !== undefined ? v.toString() : v);
let input = '';
process.stdin.on('data', (d) => { input += d; });
process.stdin.on('end', () => {
  for (const line of input.split('\n')) {
    if (!line.trim()) continue;
    const req = JSON.parse(line);
    let out;
    try {
      if (req.decode !== undefined) {
        const buf = Buffer.from(req.decode, 'base64');
        const raw = proto.Payload.toObject(proto.Payload.decode(buf), { longs: String, defaults: false });
        out = { payload: spb.decodePayload(buf), raw };
      } else {
        out = { b64: Buffer.from(spb.encodePayload(req.encode)).toString('base64') };
      }
    } catch (e) {
      out = { error: String(e) };
    }
    process.stdout.write(JSON.stringify(out, long) + '\n');
  }
});
