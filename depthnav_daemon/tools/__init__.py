"""Developer and installer tools: the kernel warm-up (``warmup``) and the soak run (``soak``)."""
