// node-opcua's client over a SignAndEncrypt channel (Basic256Sha256) with a user name
// against a running softplc (issue 31); prints one JSON report on stdout that
// tests/opcua/test_node_opcua.py judges. node-opcua makes its own client certificate (in
// $HOME's PKI folder) at the first run: softplc refuses it until `softplc trust accept`.
// Usage: node secure.js <endpoint url> <user> <password>
"use strict";
const {
  OPCUAClient, AttributeIds, MessageSecurityMode, SecurityPolicy, UserTokenType, resolveNodeId,
} = require("node-opcua-client");

const [url, userName, password] = process.argv.slice(2);
const report = {};
const hardStop = setTimeout(() => finish("the script's own 40 s bound passed"), 40000);

function finish(error) {
  if (error) report.error = String(error && error.message ? error.message : error);
  process.stdout.write(JSON.stringify(report) + "\n");
  process.exit(0);
}

async function main() {
  const client = OPCUAClient.create({
    endpointMustExist: false, applicationName: "softplc-node-test",
    securityMode: MessageSecurityMode.SignAndEncrypt, securityPolicy: SecurityPolicy.Basic256Sha256,
    connectionStrategy: { maxRetry: 0 },
  });
  try {
    await client.connect(url);
    report.channel = "open";
    const session = await client.createSession({ type: UserTokenType.UserName, userName, password });
    report.session = "activated";
    const ns = (await session.readNamespaceArray()).indexOf("urn:softplc");
    const id = (text) => resolveNodeId(`ns=${ns};s=${text}`);
    report.userExecutableSuspend = (await session.read(
      { nodeId: id("PLC.Program.Suspend"), attributeId: AttributeIds.UserExecutable })).value.value;
    const suspend = await session.call({ objectId: id("PLC.Program"), methodId: id("PLC.Program.Suspend") });
    report.suspend = suspend.statusCode.name;
    const resume = await session.call({ objectId: id("PLC.Program"), methodId: id("PLC.Program.Resume") });
    report.resume = resume.statusCode.name;
    await session.close();
  } finally {
    await client.disconnect();
  }
}

main().then(() => { clearTimeout(hardStop); finish(); }, (err) => { clearTimeout(hardStop); finish(err); });
