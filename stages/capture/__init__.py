"""Capture formats and bits: the at-rest bit packing, .dat frames, the megapixel camera's line packets, unpacked 0/1 spike arrays. Imports: stages' own errors, numbers."""
