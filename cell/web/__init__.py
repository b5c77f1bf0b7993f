"""The operator screen: a web page served beside the OPC UA server by `run-cell serve`.

It holds a LineServiceAPI and nothing else: commands go through the service's command
table into the one state machine; state and frames come back as pushed events.
"""
