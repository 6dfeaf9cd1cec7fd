// An independent OPC UA client (node-opcua) against a running softplc: it gathers what it saw
// and prints one JSON report on stdout; tests/opcua/test_node_opcua.py judges it.
// Usage: node interop.js <endpoint url> <operator password> <pid of the OPC UA process>
"use strict";
const {
  OPCUAClient, AttributeIds, DataType, StatusCodes, TimestampsToReturn, UserTokenType,
  ClientSubscription, ClientMonitoredItem, constructEventFilter, resolveNodeId,
} = require("node-opcua-client");

const [url, password, pidText] = process.argv.slice(2);
const report = { steps: [] };
const started = Date.now();
const log = (text) => process.stderr.write(`${((Date.now() - started) / 1000).toFixed(2)}s ${text}\n`);
const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));
const hardStop = setTimeout(() => finish("the script's own 55 s bound passed"), 55000);

function finish(error) {
  if (error) report.error = String(error && error.stack ? error.stack : error);
  report.seconds = (Date.now() - started) / 1000;
  process.stdout.write(JSON.stringify(report) + "\n");
  process.exit(0);
}

async function until(probe, timeoutMs, what) {
  const deadline = Date.now() + timeoutMs;
  for (;;) {
    const value = await probe();
    if (value) return value;
    if (Date.now() > deadline) throw new Error(`${what}: not within ${timeoutMs} ms`);
    await sleep(50);
  }
}

async function main() {
  const client = OPCUAClient.create({
    endpointMustExist: false, keepSessionAlive: true, requestedSessionTimeout: 30000,
    connectionStrategy: { initialDelay: 200, maxDelay: 1000, maxRetry: 100 },
  });
  client.on("connection_lost", () => { report.lostAt = Date.now(); log("connection lost"); });
  client.on("after_reconnection", () => log("reconnected"));
  await client.connect(url);
  const reader = OPCUAClient.create({ endpointMustExist: false,
    connectionStrategy: { maxRetry: 0 } });  // softplc: one session per connection
  await reader.connect(url);
  const anonymous = await reader.createSession();
  const operator = await client.createSession(
    { type: UserTokenType.UserName, userName: "operator", password });
  const ns = (await operator.readNamespaceArray()).indexOf("urn:softplc");
  const id = (text) => resolveNodeId(`ns=${ns};s=${text}`);
  report.ns = ns;

  // Browse: the symbols and the Program's methods, by browse name.
  const symbols = await operator.browse(id("PLC.Symbols").toString());
  report.symbols = symbols.references.map((r) => r.browseName.name).sort();
  const program = await operator.browse(id("PLC.Program").toString());
  const methods = {};
  for (const r of program.references) methods[r.browseName.name] = r.nodeId;

  // Read with timestamps.
  const [count] = await operator.read([{ nodeId: id("PLC.Status.ScanCount"), attributeId: AttributeIds.Value }], 0);
  report.read = {
    status: count.statusCode.name, value: count.value.value,
    source: count.sourceTimestamp && count.sourceTimestamp.getTime(),
    server: count.serverTimestamp && count.serverTimestamp.getTime(), now: Date.now(),
  };
  const access = async (session, nodeId, attributeId) =>
    (await session.read({ nodeId, attributeId })).value.value;
  report.access = {
    anonymousUserAccessLevel: await access(anonymous, id("PLC.Symbols.hold"), AttributeIds.UserAccessLevel),
    operatorUserAccessLevel: await access(operator, id("PLC.Symbols.hold"), AttributeIds.UserAccessLevel),
    anonymousUserExecutableSuspend: await access(anonymous, methods.Suspend, AttributeIds.UserExecutable),
    operatorUserExecutableSuspend: await access(operator, methods.Suspend, AttributeIds.UserExecutable),
  };

  // Writes.
  const write = async (session, text, dataType, value) => (await session.write({
    nodeId: id(text), attributeId: AttributeIds.Value, value: { value: { dataType, value } },
  })).name;
  report.writes = {
    anonymous: await write(anonymous, "PLC.Symbols.hold", DataType.Boolean, true),
    boolean: await write(operator, "PLC.Symbols.hold", DataType.Boolean, true),
    uint16ToBoolean: await write(operator, "PLC.Symbols.hold", DataType.UInt16, 1),
    int32ToUInt16: await write(operator, "PLC.Symbols.parts_delivered", DataType.Int32, 3),
    unknown: await write(operator, "PLC.Symbols.no_such", DataType.Boolean, true),
  };
  await anonymous.close();
  await reader.disconnect();
  report.writes.holdReadBack = await until(
    async () => (await operator.read({ nodeId: id("PLC.Symbols.hold") })).value.value === true,
    5000, "hold written back");
  await write(operator, "PLC.Symbols.hold", DataType.Boolean, false);

  // A subscription: data changes of ScanCount, events on the Server object.
  const subscription = ClientSubscription.create(operator, {
    requestedPublishingInterval: 100, requestedLifetimeCount: 600,
    requestedMaxKeepAliveCount: 10, publishingEnabled: true,
  });
  const changes = [];
  const item = ClientMonitoredItem.create(subscription,
    { nodeId: id("PLC.Status.ScanCount"), attributeId: AttributeIds.Value },
    { samplingInterval: 100, queueSize: 10, discardOldest: true }, TimestampsToReturn.Both);
  item.on("changed", (dv) => changes.push({ at: Date.now(), value: dv.value.value,  // UInt64: [hi, lo]
    status: dv.statusCode.name }));
  const events = [];
  const eventItem = ClientMonitoredItem.create(subscription,
    { nodeId: resolveNodeId("i=2253"), attributeId: AttributeIds.EventNotifier },
    { queueSize: 100, filter: constructEventFilter(["EventType", "Message"]) },
    TimestampsToReturn.Both);
  eventItem.on("changed", (fields) => events.push({ type: fields[0].value.toString(),
    message: fields[1].value && fields[1].value.text }));
  await until(() => changes.length > 0, 10000, "first data change");

  // Every Part 10 method in each state it meets (the PLC was started: Running).
  const state = async () => (await operator.read({ nodeId: id("PLC.Program.CurrentState") })).value.value.text;
  const plan = [["Start", "Running"], ["Reset", "Running"], ["Resume", "Running"],
    ["Suspend", "Suspended"], ["Start", "Suspended"], ["Suspend", "Suspended"],
    ["Resume", "Running"], ["Halt", "Halted"], ["Start", "Halted"], ["Reset", "Ready"],
    ["Resume", "Ready"], ["Halt", "Halted"], ["Reset", "Ready"], ["Start", "Running"]];
  report.calls = [];
  for (const [method, expected] of plan) {
    const result = await operator.call({ objectId: id("PLC.Program"), methodId: methods[method], inputArguments: [] });
    let after = await state();
    if (after !== expected) {
      after = await until(async () => { const s = await state(); return s === expected && s; }, 3000,
        `${method} -> ${expected}`).catch(() => after);
    }
    report.calls.push({ method, status: result.statusCode.name, after });
  }
  await sleep(500);  // the last transition event reaches the subscription
  report.events = events;

  // Restart recovery: kill -9 of the OPC UA process; the subscription delivers again.
  const before = changes.length;
  const killedAt = Date.now();
  process.kill(Number(pidText), "SIGKILL");
  log(`killed ${pidText}`);
  await until(() => report.lostAt, 10000, "connection lost after kill -9");
  const again = await until(() => changes.slice(before).find((c) => c.at > report.lostAt + 100),
    40000, "a data change after the restart");
  report.recovery = { seconds: (again.at - killedAt) / 1000, value: again.value, status: again.status };
  log(`delivering again after ${report.recovery.seconds} s`);
  clearTimeout(hardStop);
  await Promise.race([client.disconnect(), sleep(3000)]);
  finish();
}

main().catch((error) => finish(error));
