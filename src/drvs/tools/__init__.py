"""The tools: the console scripts' launcher (_entry), process launching, the demo, certificates,
the byte meter. They may use every layer below them."""
