// Eclipse Tahu's own Sparkplug B codec (npm sparkplug-payload) against the cell's payloads.
// argv[2]: hex of a payload the cell encoded. Prints one JSON line: that payload as Tahu decodes
// it, and the hex of a command Tahu encodes (a rebirth request and two signed integers).
"use strict";
const sparkplug = require("sparkplug-payload").get("spBv1.0");

const plain = (v) => (v !== null && typeof v === "object" && "low" in v && "high" in v ? v.toString() : v);
const decoded = sparkplug.decodePayload(Buffer.from(process.argv[2], "hex"));
const metrics = decoded.metrics.map((m) => ({ name: m.name, type: m.type, value: plain(m.value) }));
const command = sparkplug.encodePayload({
  timestamp: 1700000000000,
  metrics: [
    { name: "Node Control/Rebirth", type: "Boolean", value: true },
    { name: "small", type: "Int16", value: -3 },
    { name: "big", type: "Int64", value: -7 },
  ],
});
console.log(JSON.stringify({ seq: plain(decoded.seq), metrics, command: Buffer.from(command).toString("hex") }));
