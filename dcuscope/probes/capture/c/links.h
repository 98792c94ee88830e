/* Where a frame leaves one pipeline and enters another (links.c): the key both ends of the link can
 * compute from what crosses it, and what the tracer keeps to find it. Above ring.h.
 *
 * RTP: a frame's packets share one (SSRC, RTP timestamp); the sender reads it from the packets a
 * sink element sends (udpsink), the receiver from the packets its depayloader took in, the
 * depayloader's output naming its packets by PTS (rtpbasedepayload gives a frame the PTS of one
 * of its packets). Shared memory (shmsink -> shmsrc): the bytes themselves, hashed whole.
 * Keys are 44 bits (a frame number's range: protocol.wire.FRAME_LIMIT): a mix of the 64, so two
 * frames of the minutes a join looks at share one with a chance of about n^2 / 2^45. */
#ifndef DCU_LINKS_H
#define DCU_LINKS_H

#include "ring.h"

/* A LINK event's code (protocol/events.py LINK_KINDS); its KEY event has the same. */
enum { LINK_RTP_OUT = 1, LINK_RTP_IN = 2, LINK_SHM_OUT = 3, LINK_SHM_IN = 4 };

#define PACKET_HISTORY 64
#define ARRIVALS 4096

/* The buffers one pad passed most recently, by PTS: the packets a depayloader's sink pad took in,
 * or the buffers a shmsrc pushed (their bytes' keys). */
typedef struct {
  GMutex lock;
  guint written;
  int64_t key_now, first_now; /* the key of the latest packet and when its first packet came */
  struct { GstClockTime pts; int64_t key, first; } entries[PACKET_HISTORY];
} DcuPackets;

/* When each RTP frame's first packet left a source element (udpsrc): the receiver's first entry. */
typedef struct {
  GMutex lock;
  guint written;
  struct { int64_t key, ts; } entries[ARRIVALS];
} DcuArrivals;

/* The RTP key of an RTP packet, or -1 when buf is not one. */
int64_t dcu_rtp_key(GstBuffer *buf);
/* The key of buf's bytes, or -1 when they cannot be read. */
int64_t dcu_bytes_key(GstBuffer *buf);

/* A buffer of key and pts passed at ts (first: when the first of a run of one key did). */
void dcu_packets_note(DcuPackets *p, GstClockTime pts, int64_t key, int64_t ts);
/* The key and first-packet time of the packets whose PTS is pts; FALSE if none is remembered. */
gboolean dcu_packets_find(DcuPackets *p, GstClockTime pts, int64_t *key, int64_t *first);

void dcu_arrivals_note(DcuArrivals *a, int64_t key, int64_t ts);
/* When the first packet of key arrived; FALSE if it is not among the remembered ones. */
gboolean dcu_arrivals_find(DcuArrivals *a, int64_t key, int64_t *ts);

/* One crossing of a frame: its LINK event (when) and KEY event (the key), pushed together. */
void dcu_link_record(DcuRing *ring, int stage, int kind, int64_t ts, int64_t key, int64_t source, int64_t frame);

#endif
