// node-opcua as a generic OPC 40501 client of lathed-opcua (tests/test_opcua.py):
// finds the machines under the Machinery Machines folder by its standard NodeId, tells the
// machine tools by their type, finds their monitored elements by type, and reads the 40501
// variables by their standard browse paths. Prints one line: RESULT and a JSON object.
//     node browse_machines.mjs opc.tcp://127.0.0.1:4840
import { OPCUAClient, AttributeIds, NodeClass, BrowseDirection, makeBrowsePath, resolveNodeId } from "node-opcua-client";

const MACHINERY = "http://opcfoundation.org/UA/Machinery/";
const MT = "http://opcfoundation.org/UA/MachineTool/";
const DI = "http://opcfoundation.org/UA/DI/";

const url = process.argv[2];
const client = OPCUAClient.create({ endpointMustExist: false, connectionStrategy: { maxRetry: 2 } });
await client.connect(url);
const session = await client.createSession();
try {
    const ns = await session.readNamespaceArray();
    const idx = (uri) => {
        const i = ns.indexOf(uri);
        if (i < 0) throw new Error(`the server has no namespace ${uri}`);
        return i;
    };
    const [mc, mt, di] = [idx(MACHINERY), idx(MT), idx(DI)];
    const id = (n, i) => resolveNodeId(`ns=${n};i=${i}`).toString();
    const MACHINE_TOOL_TYPE = id(mt, 13), SPINDLE = id(mt, 22), CHANNEL = id(mt, 16);
    const Q = { mc, mt, di, ua: 0 };
    // "mt:Monitoring/mt:MachineTool" -> "/3:Monitoring/3:MachineTool" with the server's indexes
    const path = (p) => p.split("/").map((s) => { const [m, n] = s.split(":"); return `/${Q[m]}:${n}`; }).join("");

    async function children(nodeId) {
        const r = await session.browse({ nodeId, browseDirection: BrowseDirection.Forward,
            referenceTypeId: "HierarchicalReferences", includeSubtypes: true, resultMask: 63 });
        return r.references.map((x) => ({ nodeId: x.nodeId.toString(), name: x.browseName.name,
            ns: x.browseName.namespaceIndex, typeDefinition: x.typeDefinition.toString(),
            nodeClass: NodeClass[x.nodeClass] }));
    }
    async function read(start, relative) {
        const [res] = await session.translateBrowsePath([makeBrowsePath(start, relative)]);
        if (!res.statusCode.isGood()) return { browse: res.statusCode.name };
        const nodeId = res.targets[0].targetId;
        const [v, dt] = await session.read([{ nodeId, attributeId: AttributeIds.Value },
                                            { nodeId, attributeId: AttributeIds.DataType }]);
        let value = v.value.value;
        if (value && typeof value === "object") value = value.text ?? value.toString();
        return { value, status: v.statusCode.name, dataType: dt.value.value.toString() };
    }
    async function eventNotifier(start, relative) {
        const [res] = await session.translateBrowsePath([makeBrowsePath(start, relative)]);
        if (!res.statusCode.isGood()) return null;
        const dv = await session.read({ nodeId: res.targets[0].targetId, attributeId: AttributeIds.EventNotifier });
        return dv.value.value;
    }

    const out = { namespaces: { machinery: mc, machineTool: mt, di }, machines: {} };
    for (const m of await children(id(mc, 1001))) {
        const entry = out.machines[m.name] = { typeDefinition: m.typeDefinition,
            machineTool: m.typeDefinition === MACHINE_TOOL_TYPE, values: {}, elements: {} };
        const get = async (p) => { entry.values[p] = await read(m.nodeId, path(p)); };
        for (const p of ["di:Identification/di:Manufacturer", "di:Identification/di:SerialNumber",
                         "di:Identification/di:ProductInstanceUri",
                         "mc:MachineryBuildingBlocks/mc:MachineryItemState/ua:CurrentState"]) await get(p);
        if (!entry.machineTool) continue;
        for (const p of ["mt:Monitoring/mt:MachineTool/mt:OperationMode",
                         "mt:Monitoring/mt:MachineTool/mc:MachineryItemState/ua:CurrentState",
                         "mt:Production/mt:ActiveProgram/mt:Name",
                         "mt:Production/mt:ActiveProgram/mt:State/ua:CurrentState",
                         "mt:Production/mt:ActiveProgram/mt:State/ua:CurrentState/ua:Number"]) await get(p);
        entry.messagesEventNotifier = await eventNotifier(m.nodeId, path("mt:Notification/mt:Messages"));
        entry.parts = (await children(m.nodeId)).map((c) => c.name).sort();
        entry.notification = (await children((await session.translateBrowsePath(
            [makeBrowsePath(m.nodeId, path("mt:Notification"))]))[0].targets[0].targetId)).map((c) => c.name).sort();
        // the monitored elements, known by their types whatever the server names them
        const monitoring = (await session.translateBrowsePath([makeBrowsePath(m.nodeId, path("mt:Monitoring"))]))[0];
        for (const e of await children(monitoring.targets[0].targetId)) {
            const names = e.typeDefinition === SPINDLE ? ["mt:Name", "mt:IsRotating", "mt:Override"]
                : e.typeDefinition === CHANNEL ? ["mt:Name", "mt:ChannelState", "mt:ChannelMode", "mt:FeedOverride"] : null;
            if (!names) continue;
            const kind = e.typeDefinition === SPINDLE ? "spindle" : "channel";
            const values = {};
            for (const n of names) values[n] = await read(e.nodeId, path(n));
            (entry.elements[kind] ??= []).push({ name: e.name, values });
        }
    }
    console.log("RESULT " + JSON.stringify(out));   // node-opcua logs to stdout too
} finally {
    await session.close();
    await client.disconnect();
}
