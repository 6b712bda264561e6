"""The HMI's ring: its web server (`server`: aiohttp on a loop in its own thread, the pages in
`static/`) and the screenshot command (`shots`: `hrc-hmi-shots`). The node is
`nodes/hmi_node.py`; the rules are `hrc_ros.core.hmi`."""
