// Reads an MCAP file front to back with @mcap/core's McapStreamReader (what the Foxglove and
// Lichtblick apps stream files with) and prints what it got as one JSON line.
import { McapStreamReader } from "@mcap/core";
import { readFileSync } from "node:fs";
const data = readFileSync(process.argv[2]);
const reader = new McapStreamReader({ validateCrcs: true });
let records = 0, messages = 0;
const step = 1 << 20;
for (let off = 0; off < data.length; off += step) {
  reader.append(data.subarray(off, Math.min(off + step, data.length)));
  let rec;
  while ((rec = reader.nextRecord())) {
    records++;
    if (rec.type === "Message") messages++;
  }
}
console.log(JSON.stringify({ records, messages, done: reader.done(), bytesRemaining: reader.bytesRemaining() }));
