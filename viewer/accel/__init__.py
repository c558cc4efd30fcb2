"""Acceleration structures any backend may reuse, one module each: a builder plus a documented
array layout with a size assert (tinybvh style). Today: the binned-SAH binary BVH (`bvh`)."""
