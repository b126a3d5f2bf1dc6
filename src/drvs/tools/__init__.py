"""The tools: the console scripts' launcher (_entry), process launching, the demo, certificates,
the byte meter, the fake cameras. They may use every layer below them."""
