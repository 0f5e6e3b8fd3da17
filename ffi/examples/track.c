/* HoloFace C API example: tracks the face in a gray PGM image over 30 video frames with local KRFWS,
 * prints the head pose per frame, and checks that bad handles are rejected.
 *
 *   cc -I ffi/include ffi/examples/track.c -L target/debug -lholoface -o track && ./track face.pgm
 *
 * Asset paths left NULL in HfOptions come from the environment (ORT_DYLIB_PATH, HOLOFACE_DETECTOR_MODEL,
 * HOLOFACE_KRFWS_MODEL, HOLOFACE_CANDIDE), else the holoface data folder that `holoface setup` fills (the
 * Makefile points HOLOFACE_HOME at .cache/holoface). An app that ships its assets passes their paths in
 * HfOptions. Exit status 0 = tracked.
 *
 * With HOLOFACE_SERVER (ip:port) and HOLOFACE_SERVER_FINGERPRINT (and HOLOFACE_TOKEN) set, it then tracks the
 * face through that alignment server too, frames paced at 15 fps on the wall clock, printing each change of
 * the aligner that answers, until the answers went remote, local (the link cut) and remote again (within
 * 150 s). scripts/arm64-link.sh runs it so on aarch64 against an x86-64 server, stopping the server for the cut. */
#define _POSIX_C_SOURCE 200809L
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "holoface.h"

static uint8_t *read_pgm(const char *path, uint32_t *w, uint32_t *h) {
    FILE *f = fopen(path, "rb");
    if (!f) return NULL;
    unsigned width, height, maxval;
    if (fscanf(f, "P5 %u %u %u", &width, &height, &maxval) != 3 || maxval != 255 || fgetc(f) == EOF) {
        fclose(f);
        return NULL;
    }
    uint8_t *px = malloc((size_t)width * height);
    if (px && fread(px, 1, (size_t)width * height, f) != (size_t)width * height) {
        free(px);
        px = NULL;
    }
    fclose(f);
    *w = width;
    *h = height;
    return px;
}

static uint64_t now_us(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

static const char *aligner_name(HfAnsweredBy by) {
    switch (by) {
        case HF_ANSWERED_BY_REMOTE_DAN: return "remote DAN (the server)";
        case HF_ANSWERED_BY_KRFWS: return "local KRFWS";
        case HF_ANSWERED_BY_LOCAL_DAN: return "local DAN";
        default: return "nobody (no face)";
    }
}

/* The face tracked through the alignment server named by HOLOFACE_SERVER: 0 when the answers went remote,
 * local and remote again, 1 otherwise. */
static int track_linked(const char *server, const uint8_t *px, uint32_t w, uint32_t h, const HfCamera *cam,
                        const float *pose) {
    HfOptions opts;
    hf_options_default(&opts);
    opts.server = server;
    opts.server_fingerprint = getenv("HOLOFACE_SERVER_FINGERPRINT");
    opts.token = getenv("HOLOFACE_TOKEN");
    /* Under emulation (qemu) the client's own work is tens of times slower than on a device: its runner may
     * give the server's answers longer than the default deadline. */
    const char *deadline = getenv("HOLOFACE_DEADLINE_MS");
    if (deadline) opts.deadline_ms = (uint32_t)strtoul(deadline, NULL, 10);
    HfTracker *t = NULL;
    if (hf_tracker_new(&opts, &t) != HF_STATUS_OK) {
        fprintf(stderr, "hf_tracker_new with server %s failed: %s\n", server, hf_last_error());
        return 1;
    }
    /* 0: waiting for the server's first answer; 1: for a local one (the cut); 2: for the server's again. */
    int phase = 0, frames = 0, counts[4] = {0, 0, 0, 0};
    HfAnsweredBy last = HF_ANSWERED_BY_NONE;
    const uint64_t start = now_us(), period = 66667u, limit = 150u * 1000000u;
    uint64_t next = start;
    HfResult r;
    while (phase < 3 && now_us() - start < limit) {
        uint64_t now = now_us();
        if (now < next) {
            struct timespec pause = {0, (long)(next - now) * 1000L};
            nanosleep(&pause, NULL);
        }
        next += period;
        uint64_t ts = now_us() - start + 1u;
        if (hf_tracker_process(t, px, w, h, w, ts, cam, pose, &r) != HF_STATUS_OK) {
            fprintf(stderr, "linked frame %d failed: %s\n", frames, hf_last_error());
            break;
        }
        if ((unsigned)r.answered_by < 4u) counts[r.answered_by]++;
        if (r.answered_by != last || frames == 0) {
            printf("linked frame %d at %.1f s: answered by %s\n", frames, (double)ts / 1e6, aligner_name(r.answered_by));
            fflush(stdout);
        }
        last = r.answered_by;
        int remote = r.answered_by == HF_ANSWERED_BY_REMOTE_DAN, local = r.answered_by == HF_ANSWERED_BY_KRFWS;
        if ((phase == 0 && remote) || (phase == 1 && local) || (phase == 2 && remote)) phase++;
        frames++;
    }
    HfLinkStatus link;
    hf_tracker_link_status(t, &link);
    printf("linked: %d frames, %d answered by the server, %d by local KRFWS, %d without a face; link state %d\n",
           frames, counts[HF_ANSWERED_BY_REMOTE_DAN], counts[HF_ANSWERED_BY_KRFWS], counts[HF_ANSWERED_BY_NONE],
           (int)link.state);
    hf_tracker_free(t);
    if (phase < 3) fprintf(stderr, "the answers did not go remote, local and remote again (reached step %d of 3)\n", phase);
    return phase == 3 ? 0 : 1;
}

int main(int argc, char **argv) {
    if (argc != 2) {
        fprintf(stderr, "usage: %s face.pgm\n", argv[0]);
        return 2;
    }
    uint32_t w, h;
    uint8_t *px = read_pgm(argv[1], &w, &h);
    if (!px) {
        fprintf(stderr, "cannot read binary 8-bit PGM %s\n", argv[1]);
        return 2;
    }
    printf("holoface %s, image %ux%u\n", hf_version(), w, h);

    /* Bad input is an error code, never a crash. */
    HfResult r;
    HfCamera cam = {500.0, 500.0, w / 2.0, h / 2.0};
    if (hf_tracker_process(NULL, px, w, h, w, 0, &cam, NULL, &r) != HF_STATUS_INVALID_HANDLE) return 3;
    if (hf_tracker_process((HfTracker *)px, px, w, h, w, 0, &cam, NULL, &r) != HF_STATUS_INVALID_HANDLE) return 3;
    printf("bad handle rejected: %s\n", hf_last_error());

    HfOptions opts;
    hf_options_default(&opts);
    HfTracker *t = NULL;
    HfStatus s = hf_tracker_new(&opts, &t);
    if (s != HF_STATUS_OK) {
        fprintf(stderr, "hf_tracker_new failed (%d): %s\n", (int)s, hf_last_error());
        free(px);
        return 1;
    }
    /* With its length, a buffer shorter than the image is refused rather than read past. */
    if (hf_tracker_process_buf(t, px, (size_t)w * h - 1, w, h, w, 0, &cam, NULL, &r) != HF_STATUS_INVALID_ARGUMENT) return 3;
    printf("short buffer rejected: %s\n", hf_last_error());
    /* A headset standing still: identity camera-to-world, 30 fps. */
    const float pose[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
    int faces = 0;
    for (int i = 0; i < 30; i++) {
        s = hf_tracker_process_buf(t, px, (size_t)w * h, w, h, w, (uint64_t)i * 33333u, &cam, pose, &r);
        if (s != HF_STATUS_OK) {
            fprintf(stderr, "frame %d failed (%d): %s\n", i, (int)s, hf_last_error());
            break;
        }
        faces += r.has_face;
        if (i % 10 == 0 || i == 29)
            printf("frame %2d face=%d by=%d nose(px)=(%.1f, %.1f) raw (%.1f, %.1f) head(m)=(%.3f, %.3f, %.3f) jaw=%.2f\n",
                   i, r.has_face, (int)r.answered_by, r.landmarks_px[2 * 30], r.landmarks_px[2 * 30 + 1],
                   r.raw_landmarks_px[2 * 30], r.raw_landmarks_px[2 * 30 + 1], r.world_position_m[0],
                   r.world_position_m[1], r.world_position_m[2], r.weights[0]);
    }
    /* No server configured: the link status says the local aligner answers. */
    HfLinkStatus link;
    if (hf_tracker_link_status(t, &link) != HF_STATUS_OK || link.state != HF_LINK_STATE_LOCAL) return 3;
    if (hf_tracker_link_status(NULL, &link) != HF_STATUS_INVALID_HANDLE) return 3;
    printf("link: state %d (local)\n", (int)link.state);
    /* Timestamps must increase in video mode. */
    HfStatus back = hf_tracker_process(t, px, w, h, w, 0, &cam, pose, &r);
    printf("old timestamp: status %d (%s)\n", (int)back, hf_last_error());
    hf_tracker_free(t);
    if (hf_tracker_free(t) != HF_STATUS_INVALID_HANDLE) return 3; /* double free is caught */

    /* Several faces: up to 3 tracked at once, each with its id (one person here: id 0 throughout). */
    HfTracker *multi = NULL;
    if (hf_tracker_new_faces(&opts, 0, &multi) != HF_STATUS_INVALID_ARGUMENT) return 3;
    if (hf_tracker_new_faces(&opts, HF_MAX_FACES + 1, &multi) != HF_STATUS_INVALID_ARGUMENT) return 3;
    if (hf_tracker_new_faces(&opts, 3, &multi) != HF_STATUS_OK) {
        fprintf(stderr, "hf_tracker_new_faces failed: %s\n", hf_last_error());
        return 1;
    }
    HfFaces all;
    all.struct_size = sizeof(HfFaces) - 1; /* a caller built against another layout is refused */
    if (hf_tracker_process_faces(multi, px, w, h, w, 0, &cam, pose, &all) != HF_STATUS_INVALID_ARGUMENT) return 3;
    printf("wrong HfFaces size rejected: %s\n", hf_last_error());
    all.struct_size = sizeof(HfFaces);
    int with_id0 = 0;
    for (int i = 0; i < 30; i++) {
        if (hf_tracker_process_faces(multi, px, w, h, w, (uint64_t)i * 33333u, &cam, pose, &all) != HF_STATUS_OK) {
            fprintf(stderr, "faces frame %d failed: %s\n", i, hf_last_error());
            return 1;
        }
        with_id0 += all.count == 1 && all.faces[0].id == 0 && all.faces[0].face.has_face;
    }
    printf("several-face tracker: %d of 30 frames with exactly face #0\n", with_id0);
    hf_tracker_free(multi);

    /* Every setting (the names and defaults of Python's TrackerOptions and the CLI's flags): the landmark
     * filter off, so the steadied landmarks are the raw ones, and 2 x 2 detector tiles. */
    HfSettings set;
    set.struct_size = sizeof(HfSettings);
    if (hf_settings_default(&set) != HF_STATUS_OK) return 3;
    set.steady = 0;
    set.detect_tiles = 2;
    HfTracker *raw = NULL;
    if (hf_tracker_new_with(&opts, &set, &raw) != HF_STATUS_OK) {
        fprintf(stderr, "hf_tracker_new_with failed: %s\n", hf_last_error());
        return 1;
    }
    int unfiltered = 0;
    for (int i = 0; i < 10; i++) {
        if (hf_tracker_process(raw, px, w, h, w, (uint64_t)i * 33333u, &cam, pose, &r) != HF_STATUS_OK) return 1;
        unfiltered += r.has_face && memcmp(r.landmarks_px, r.raw_landmarks_px, sizeof r.landmarks_px) == 0;
    }
    printf("steady = 0: %d of 10 frames with landmarks equal to the raw ones\n", unfiltered);
    /* Blendshapes: HF_BLENDSHAPES ARKit-named coefficients in [0, 1], named by hf_blendshape_name. */
    int bounded = r.has_face;
    for (uint32_t i = 0; i < HF_BLENDSHAPES; i++) {
        bounded &= r.blendshapes[i] >= 0.0f && r.blendshapes[i] <= 1.0f && hf_blendshape_name(i) != NULL;
    }
    if (!bounded || hf_blendshape_name(HF_BLENDSHAPES) != NULL) return 3;
    printf("%s %.2f, %s %.2f\n", hf_blendshape_name(15), r.blendshapes[15], hf_blendshape_name(0), r.blendshapes[0]);
    hf_tracker_free(raw);
    set.detect_tiles = 99;
    if (hf_tracker_new_with(&opts, &set, &raw) != HF_STATUS_INVALID_ARGUMENT) return 3;
    printf("detect_tiles 99 rejected: %s\n", hf_last_error());
    printf("%d of 30 frames with a face\n", faces);
    const char *server = getenv("HOLOFACE_SERVER");
    int linked = server ? track_linked(server, px, w, h, &cam, pose) : 0;
    free(px);
    return (linked == 0 && s == HF_STATUS_OK && back == HF_STATUS_INVALID_ARGUMENT && faces >= 25 && with_id0 >= 25 && unfiltered >= 8) ? 0 : 1;
}
