/* DeepStream's batch metadata, read without NVIDIA's headers (deepstream.c). Above frames.h. */
#ifndef DCU_DEEPSTREAM_H
#define DCU_DEEPSTREAM_H

#include "frames.h"

/* The frames of buf's NvDsBatchMeta as a frames structure (origin `now` for all), or NULL. */
GstStructure *dcu_deepstream_frames(GstBuffer *buf, int64_t now);

#endif
