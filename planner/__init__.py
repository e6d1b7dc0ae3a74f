"""Pure computation: rig geometry, optics, visibility, the focus cost and its optimisers, TSDF.

No asyncio, no devices: numbers in, numbers out.
"""
