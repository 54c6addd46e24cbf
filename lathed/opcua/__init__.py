"""lathed-opcua: the line as an OPC UA server beside the daemon (see lathed.opcua.app)."""
