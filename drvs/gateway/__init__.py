"""The HTTP gateway's decisions, without ROS: request bodies, DRVS status -> HTTP, tokens, watches
and their Server-Sent Events, the route table and its OpenAPI document, and the aiohttp
application that wires them to a DRVS client. The contract: docs/gateway.md.
"""
