/* Link keys and what the tracer remembers to find them (links.h). */

#include "links.h"

#include <string.h>

#define KEY_MASK ((INT64_C(1) << 44) - 1)

static inline uint64_t mix64(uint64_t z) { /* splitmix64's finaliser */
  z = (z ^ (z >> 30)) * UINT64_C(0xbf58476d1ce4e5b9);
  z = (z ^ (z >> 27)) * UINT64_C(0x94d049bb133111eb);
  return z ^ (z >> 31);
}

static inline int64_t to_key(uint64_t h) { return (int64_t)(mix64(h) & KEY_MASK); }

int64_t dcu_rtp_key(GstBuffer *buf) {
  guint8 head[12];
  if (gst_buffer_extract(buf, 0, head, sizeof head) != sizeof head || (head[0] >> 6) != 2) return -1;
  uint32_t rtptime = (uint32_t)head[4] << 24 | (uint32_t)head[5] << 16 | (uint32_t)head[6] << 8 | head[7];
  uint32_t ssrc = (uint32_t)head[8] << 24 | (uint32_t)head[9] << 16 | (uint32_t)head[10] << 8 | head[11];
  return to_key((uint64_t)ssrc << 32 | rtptime);
}

int64_t dcu_bytes_key(GstBuffer *buf) {
  GstMapInfo map;
  if (!gst_buffer_map(buf, &map, GST_MAP_READ)) return -1;
  /* Four independent lanes of 64-bit words: memory-bound, about a byte per cycle or better. */
  uint64_t lane[4] = {UINT64_C(0x9e3779b97f4a7c15), UINT64_C(0xc2b2ae3d27d4eb4f), UINT64_C(0x165667b19e3779f9),
                      UINT64_C(0x27d4eb2f165667c5)};
  const guint8 *d = map.data;
  gsize n = map.size, i = 0;
  for (; i + 32 <= n; i += 32) {
    for (int k = 0; k < 4; k++) {
      uint64_t w;
      memcpy(&w, d + i + 8 * k, 8);
      lane[k] = (lane[k] ^ w) * UINT64_C(0x100000001b3);
    }
  }
  uint64_t tail = 0;
  for (; i < n; i++) tail = (tail << 8 | d[i]) * 31;
  gst_buffer_unmap(buf, &map);
  uint64_t h = (uint64_t)n;
  for (int k = 0; k < 4; k++) h = mix64(h ^ lane[k]);
  return to_key(h ^ tail);
}

void dcu_packets_note(DcuPackets *p, GstClockTime pts, int64_t key, int64_t ts) {
  g_mutex_lock(&p->lock);
  if (p->written == 0 || key != p->key_now) {
    p->key_now = key;
    p->first_now = ts;
  }
  guint slot = p->written++ % PACKET_HISTORY;
  p->entries[slot].pts = pts;
  p->entries[slot].key = key;
  p->entries[slot].first = p->first_now;
  g_mutex_unlock(&p->lock);
}

gboolean dcu_packets_find(DcuPackets *p, GstClockTime pts, int64_t *key, int64_t *first) {
  gboolean found = FALSE;
  if (!GST_CLOCK_TIME_IS_VALID(pts)) return FALSE;
  g_mutex_lock(&p->lock);
  guint oldest = p->written > PACKET_HISTORY ? p->written - PACKET_HISTORY : 0;
  for (guint k = p->written; k > oldest && !found; k--) {
    const guint slot = (k - 1) % PACKET_HISTORY;
    if (p->entries[slot].pts == pts) {
      *key = p->entries[slot].key;
      *first = p->entries[slot].first;
      found = TRUE;
    }
  }
  g_mutex_unlock(&p->lock);
  return found;
}

void dcu_arrivals_note(DcuArrivals *a, int64_t key, int64_t ts) {
  g_mutex_lock(&a->lock);
  guint slot = a->written++ % ARRIVALS;
  a->entries[slot].key = key;
  a->entries[slot].ts = ts;
  g_mutex_unlock(&a->lock);
}

gboolean dcu_arrivals_find(DcuArrivals *a, int64_t key, int64_t *ts) {
  /* The earliest entry of the key: a packet that came late (reordered) after others is noted again. */
  gboolean found = FALSE;
  g_mutex_lock(&a->lock);
  guint oldest = a->written > ARRIVALS ? a->written - ARRIVALS : 0;
  for (guint k = a->written; k > oldest; k--) {
    const guint slot = (k - 1) % ARRIVALS;
    if (a->entries[slot].key == key && (!found || a->entries[slot].ts < *ts)) {
      *ts = a->entries[slot].ts;
      found = TRUE;
    }
  }
  g_mutex_unlock(&a->lock);
  return found;
}

void dcu_link_record(DcuRing *ring, int stage, int kind, int64_t ts, int64_t key, int64_t source, int64_t frame) {
  DcuEvent pair[2] = {{ts, frame, (int32_t)source, (int16_t)stage, P_LINK, (int8_t)kind},
                      {ts, key, (int32_t)source, (int16_t)stage, P_KEY, (int8_t)kind}};
  dcu_push(ring, pair, 2);
}
