/* Host build of the reference firmware: serves the protocol on a pseudo-terminal, with a stage
 * behind its DAC/ADC. Prints the pty path (or the --link symlink) on stdout, logs on stderr,
 * SIGUSR1 unplugs the pty for --unplug-s seconds, SIGTERM/SIGINT exit 0.
 *
 * The stage: --stage-cmd runs a helper (python -m hil_sim.stage_pipe) that steps hil_sim's
 * stage over a pipe; without it, a linear stage (0.1 um/V, no dynamics) stands behind the DAC. */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "fw_core.h"

#define MAX_BLOCK 8192u
#define MAX_PENDING 8u

/* A block of ticks sent to the stage helper, waiting for its sensed positions. */
typedef struct pending {
    unsigned n_rows, n_adc;
    int16_t *dst[MAX_BLOCK];
    uint16_t row[MAX_BLOCK];
} pending;
#define BACKLOG_MAX (8u << 20)

static fw_board board;
static volatile sig_atomic_t sig_stop, sig_unplug;

typedef struct host {
    int master;
    char slave[128];
    const char *link;
    bool present;
    uint8_t *backlog;
    size_t backlog_len;
    /* sample timer */
    uint32_t rate;
    uint64_t t0_us, ticks_done;
    /* stage */
    FILE *to_stage;
    int from_stage;
    pending pend[MAX_PENDING];
    unsigned pend_head, pend_tail;
    uint8_t *rbuf;
    size_t rbuf_len;
    unsigned C;
    float amp_lo[FW_MAX_CHANNELS], amp_hi[FW_MAX_CHANNELS];
    float volts[MAX_BLOCK][FW_MAX_CHANNELS];
    unsigned n_rows, n_adc;
    float out_v[FW_MAX_CHANNELS];
    uint64_t stage_us;
} host;

static host H;
static pending block; /* the conversions of the ticks run in this loop iteration */

static uint64_t now_us(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000u + (uint64_t)ts.tv_nsec / 1000u;
}

static void logline(const char *level, const char *text) {
    struct timespec ts;
    clock_gettime(CLOCK_REALTIME, &ts);
    struct tm tm;
    localtime_r(&ts.tv_sec, &tm);
    char stamp[32];
    strftime(stamp, sizeof stamp, "%Y-%m-%d %H:%M:%S", &tm);
    fprintf(stderr, "%s,%03ld fw_host[%d] %s: %s\n", stamp, ts.tv_nsec / 1000000L, (int)getpid(), level, text);
    fflush(stderr);
}

static void die(const char *what) {
    fprintf(stderr, "piezod-fw-host: error: %s: %s\n", what, strerror(errno));
    exit(2);
}

/* -- HAL ------------------------------------------------------------------------------------ */

static void hal_tx(void *ctx, const uint8_t *data, size_t n) {
    host *h = ctx;
    if (h->master < 0 || !h->present) return;
    if (h->backlog_len + n > BACKLOG_MAX) {
        logline("WARNING", "host not reading: output dropped");
        return;
    }
    memcpy(h->backlog + h->backlog_len, data, n);
    h->backlog_len += n;
}

static float code_to_v(const host *h, unsigned c, int16_t code) {
    (void)h;
    if (!board.configured) return 0.0f;
    const fw_channel *ch = &board.conf.ch[c];
    return (float)((double)ch->dac_offset_v + (double)ch->dac_v_per_code * code);
}

static void hal_dac(void *ctx, const int16_t *codes, unsigned C) {
    host *h = ctx;
    for (unsigned c = 0; c < C; c++) h->out_v[c] = code_to_v(h, c, codes[c]);
    if (board.state == FW_RUNNING && h->n_rows < MAX_BLOCK) {
        memcpy(h->volts[h->n_rows], h->out_v, sizeof h->out_v);
        h->n_rows++;
    }
}

static void hal_adc(void *ctx, int16_t *dst, unsigned C) {
    host *h = ctx;
    (void)C;
    if (h->n_rows == 0 || h->n_adc >= MAX_BLOCK) return;
    block.dst[h->n_adc] = dst;
    block.row[h->n_adc] = (uint16_t)(h->n_rows - 1u);
    h->n_adc++;
}

static void hal_timer(void *ctx, uint32_t rate) {
    host *h = ctx;
    h->rate = rate;
    h->t0_us = now_us();
    h->ticks_done = 0;
    if (rate) h->stage_us = h->t0_us;
}

static unsigned long sync_changes;
static uint8_t sync_level;

static void hal_sync(void *ctx, uint8_t lines) {
    (void)ctx;
    if (lines != sync_level) sync_changes++;
    if ((lines & 4u) && !(sync_level & 4u)) {
        char line[80];
        snprintf(line, sizeof line, "sync: frame clock high at index %llu", (unsigned long long)board.last_played);
        logline("INFO", line);
    }
    sync_level = lines;
}

static void hal_log(void *ctx, const char *text) {
    (void)ctx;
    logline(strncmp(text, "watchdog", 8) == 0 || strncmp(text, "underrun", 8) == 0 ? "WARNING" : "INFO", text);
}

/* -- the stage ------------------------------------------------------------------------------ */

static double linear_gain_um_per_v = 0.1;

static double dac_code_to_adc(unsigned c, float pos_um) {
    const fw_channel *ch = &board.conf.ch[c];
    double code = rint(((double)pos_um - ch->adc_offset_um) / ch->adc_um_per_code);
    return code < -32768.0 ? -32768.0 : code > 32767.0 ? 32767.0 : code;
}

/* Fill the conversions of a block from the positions (um) of its rows. */
static void complete(host *h, const pending *p, const float *pos) {
    for (unsigned k = 0; k < p->n_adc; k++)
        for (unsigned c = 0; c < h->C; c++)
            p->dst[k][c] = (int16_t)dac_code_to_adc(c, pos[(size_t)p->row[k] * h->C + c]);
    fw_sensor_done(&board, p->n_adc);
}

/* Read what the stage helper answered; complete the blocks whose answer is whole. With `wait`,
 * block until at least the oldest pending block is complete. */
static void stage_collect(host *h, bool wait) {
    while (h->pend_tail != h->pend_head) {
        const pending *p = &h->pend[h->pend_tail % MAX_PENDING];
        size_t need = (size_t)p->n_rows * h->C * sizeof(float);
        if (h->rbuf_len >= need) {
            complete(h, p, (const float *)(void *)h->rbuf);
            memmove(h->rbuf, h->rbuf + need, h->rbuf_len - need);
            h->rbuf_len -= need;
            h->pend_tail++;
            wait = false;
            continue;
        }
        struct pollfd pfd = {.fd = h->from_stage, .events = POLLIN};
        if (poll(&pfd, 1, wait ? 10000 : 0) <= 0) {
            if (wait) {
                errno = ETIMEDOUT;
                die("stage helper silent for 10 s");
            }
            return;
        }
        ssize_t n = read(h->from_stage, h->rbuf + h->rbuf_len, (size_t)MAX_BLOCK * FW_MAX_CHANNELS * 4u - h->rbuf_len);
        if (n <= 0) {
            errno = EPIPE;
            die("stage helper exited");
        }
        h->rbuf_len += (size_t)n;
    }
}

/* Send rows[0..n) of volts (each dt long) to the stage; `p` names the conversions they feed. */
static void stage_send(host *h, unsigned n, double dt, float (*rows)[FW_MAX_CHANNELS], const pending *p) {
    if (!h->to_stage) {
        static float pos[MAX_BLOCK * FW_MAX_CHANNELS];
        for (unsigned j = 0; j < n; j++)
            for (unsigned c = 0; c < h->C; c++) pos[j * h->C + c] = (float)(linear_gain_um_per_v * rows[j][c]);
        if (p) complete(h, p, pos);
        return;
    }
    if (h->pend_head - h->pend_tail == MAX_PENDING) stage_collect(h, true);
    pending *slot = &h->pend[h->pend_head % MAX_PENDING];
    if (p) {
        slot->n_adc = p->n_adc;
        memcpy(slot->dst, p->dst, p->n_adc * sizeof p->dst[0]);
        memcpy(slot->row, p->row, p->n_adc * sizeof p->row[0]);
    } else {
        slot->n_adc = 0;
    }
    slot->n_rows = n;
    h->pend_head++;
    uint32_t nn = n;
    if (fwrite(&nn, 4, 1, h->to_stage) != 1 || fwrite(&dt, 8, 1, h->to_stage) != 1) die("stage pipe");
    for (unsigned j = 0; j < n; j++)
        if (fwrite(rows[j], sizeof(float), h->C, h->to_stage) != h->C) die("stage pipe");
    if (fflush(h->to_stage) != 0) die("stage pipe");
}

static void run_stage_block(host *h) {
    if (h->n_rows == 0) return;
    double dt = 1.0 / (h->rate ? h->rate : board.conf.sample_rate_hz);
    block.n_rows = h->n_rows;
    block.n_adc = h->n_adc;
    stage_send(h, h->n_rows, dt, h->volts, &block);
    h->n_rows = h->n_adc = 0;
}

static void idle_stage(host *h, uint64_t t) {
    if (t - h->stage_us < 50000u) return; /* between runs the stage evolves (creep) in 50 ms blocks */
    unsigned n = (unsigned)((t - h->stage_us + 999u) / 1000u);
    if (n > MAX_BLOCK) n = MAX_BLOCK;
    double dt = (double)(t - h->stage_us) * 1e-6 / n;
    for (unsigned j = 0; j < n; j++) memcpy(h->volts[j], h->out_v, sizeof h->out_v);
    stage_send(h, n, dt, h->volts, NULL);
    h->stage_us = t;
}

static void start_stage(host *h, const char *cmd) {
    int to[2], from[2];
    if (pipe(to) || pipe(from)) die("pipe");
    pid_t pid = fork();
    if (pid < 0) die("fork");
    if (pid == 0) {
        dup2(to[0], 0);
        dup2(from[1], 1);
        close(to[1]);
        close(from[0]);
        execl("/bin/sh", "sh", "-c", cmd, (char *)NULL);
        _exit(127);
    }
    close(to[0]);
    close(from[1]);
    h->to_stage = fdopen(to[1], "wb");
    h->from_stage = from[0];
    FILE *head = fdopen(dup(from[0]), "rb");
    char magic[4];
    uint32_t C;
    if (!head || fread(magic, 1, 4, head) != 4 || memcmp(magic, "PZST", 4) || fread(&C, 4, 1, head) != 1 ||
        C < 1 || C > FW_MAX_CHANNELS) {
        fprintf(stderr, "piezod-fw-host: error: --stage-cmd %s: no stage header\n", cmd);
        exit(2);
    }
    h->C = C;
    for (unsigned c = 0; c < C; c++)
        if (fread(&h->amp_lo[c], 4, 1, head) != 1 || fread(&h->amp_hi[c], 4, 1, head) != 1) {
            fprintf(stderr, "piezod-fw-host: error: --stage-cmd %s: short stage header\n", cmd);
            exit(2);
        }
    fclose(head);
}

/* -- the pty -------------------------------------------------------------------------------- */

static void pty_open(host *h) {
    int m = posix_openpt(O_RDWR | O_NOCTTY);
    if (m < 0 || grantpt(m) || unlockpt(m)) die("posix_openpt");
    const char *name = ptsname(m);
    if (!name) die("ptsname");
    snprintf(h->slave, sizeof h->slave, "%s", name);
    int s = open(h->slave, O_RDWR | O_NOCTTY);
    if (s < 0) die("open pty slave");
    struct termios t;
    if (tcgetattr(s, &t)) die("tcgetattr");
    cfmakeraw(&t);
    if (tcsetattr(s, TCSANOW, &t)) die("tcsetattr");
    close(s);
    fcntl(m, F_SETFL, fcntl(m, F_GETFL) | O_NONBLOCK);
    h->master = m;
    h->present = false;
    h->backlog_len = 0;
    if (h->link) {
        char tmp[4200];
        snprintf(tmp, sizeof tmp, "%s.%d.tmp", h->link, (int)getpid());
        unlink(tmp);
        if (symlink(h->slave, tmp) || rename(tmp, h->link)) die("--link");
    }
}

/* The link goes before the master: once the master is closed its pty number may be handed to
 * another process, and a host reopening the link must not find that port there. */
static void pty_close(host *h) {
    if (h->link) unlink(h->link);
    if (h->master >= 0) close(h->master);
    h->master = -1;
    h->present = false;
    h->backlog_len = 0;
}

static void set_present(host *h, bool p) {
    if (p != h->present) {
        char line[200];
        snprintf(line, sizeof line, "host %s %s", p ? "opened" : "closed", h->slave);
        logline("INFO", line);
        h->present = p;
        if (!p) h->backlog_len = 0;
    }
}

static void pty_read(host *h, uint64_t t) {
    static uint8_t buf[65536];
    for (int k = 0; k < 16 && h->master >= 0; k++) {
        ssize_t n = read(h->master, buf, sizeof buf);
        if (n > 0) {
            set_present(h, true);
            fw_rx(&board, buf, (size_t)n, t);
            continue;
        }
        if (n < 0 && errno == EAGAIN) set_present(h, true);
        else if (n < 0 && errno == EIO) set_present(h, false);
        return;
    }
}

static void pty_write(host *h) {
    while (h->master >= 0 && h->present && h->backlog_len) {
        ssize_t n = write(h->master, h->backlog, h->backlog_len);
        if (n < 0) {
            if (errno == EIO) set_present(h, false);
            return;
        }
        memmove(h->backlog, h->backlog + n, h->backlog_len - (size_t)n);
        h->backlog_len -= (size_t)n;
    }
}

static void on_signal(int sig) {
    if (sig == SIGUSR1) sig_unplug = 1;
    else sig_stop = 1;
}

int main(int argc, char **argv) {
    const char *stage_cmd = NULL;
    double unplug_s = 2.0;
    uint32_t serial = 0x51A0C001u, rate_max = 200000u;
    uint8_t no_sensor = 0;
    H.master = -1;
    H.C = 3;
    for (unsigned c = 0; c < FW_MAX_CHANNELS; c++) H.amp_lo[c] = -250.0f, H.amp_hi[c] = 250.0f;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "--link") && v) H.link = v, i++;
        else if (!strcmp(a, "--stage-cmd") && v) stage_cmd = v, i++;
        else if (!strcmp(a, "--unplug-s") && v) unplug_s = atof(v), i++;
        else if (!strcmp(a, "--serial") && v) serial = (uint32_t)strtoul(v, NULL, 0), i++;
        else if (!strcmp(a, "--rate-max") && v) rate_max = (uint32_t)strtoul(v, NULL, 0), i++;
        else if (!strcmp(a, "--channels") && v) H.C = (unsigned)atoi(v), i++;
        else if (!strcmp(a, "--no-position-sensor")) no_sensor = 1;
        else {
            fprintf(stderr,
                    "usage: piezod-fw-host [--link PATH] [--stage-cmd CMD] [--unplug-s S] [--serial N] "
                    "[--rate-max HZ] [--channels C] [--no-position-sensor]\n");
            return 2;
        }
    }
    if (H.C < 1 || H.C > FW_MAX_CHANNELS || !(unplug_s >= 0)) {
        fprintf(stderr, "piezod-fw-host: error: --channels must lie in [1, 8], --unplug-s >= 0\n");
        return 2;
    }
    signal(SIGPIPE, SIG_IGN);
    if (stage_cmd) start_stage(&H, stage_cmd);
    /* the host program's only allocations; the core has none */
    H.backlog = malloc(BACKLOG_MAX);
    H.rbuf = malloc((size_t)MAX_BLOCK * FW_MAX_CHANNELS * sizeof(float));
    if (!H.backlog || !H.rbuf) die("malloc");
    fw_caps caps = {.fw_major = 1, .fw_minor = 0, .fw_patch = 0, .n_channels = (uint8_t)H.C,
                    .dac_bits = 16, .adc_bits = 16, .sync_outputs = 3, .max_samples_per_frame = fw_max_rows(H.C),
                    .sample_rate_min_hz = 1, .sample_rate_max_hz = rate_max, .sample_clock_hz = 0,
                    .board_serial = serial, .no_position_sensor = no_sensor};
    for (unsigned c = 0; c < H.C; c++) caps.amp_v_min[c] = H.amp_lo[c], caps.amp_v_max[c] = H.amp_hi[c];
    fw_hal hal = {.ctx = &H, .tx = hal_tx, .dac_write = hal_dac, .adc_read = hal_adc, .timer = hal_timer,
                  .sync_out = hal_sync, .log = hal_log};
    uint64_t t = now_us();
    H.stage_us = t;
    fw_init(&board, &caps, &hal, t);
    board.sens_deferred = true; /* the stage helper answers later: conversions complete in stage_collect */
    struct sigaction sa = {0};
    sa.sa_handler = on_signal;
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGUSR1, &sa, NULL);
    pty_open(&H);
    char info[160];
    snprintf(info, sizeof info, "reference firmware (host build): %u channels, FIFO %u, serial 0x%08x", H.C,
             FW_FIFO_DEPTH, serial);
    logline("INFO", info);
    printf("%s\n", H.link ? H.link : H.slave);
    fflush(stdout);
    uint64_t replug_at = 0;
    while (!sig_stop) {
        struct pollfd pfd = {.fd = H.master, .events = POLLIN | (H.backlog_len ? POLLOUT : 0)};
        if (H.master >= 0 && H.present) poll(&pfd, 1, 2);
        else usleep(2000);
        t = now_us();
        pty_read(&H, t);
        if (H.rate && board.state == FW_RUNNING) {
            uint64_t due = t > H.t0_us ? (t - H.t0_us) * H.rate / 1000000u : 0u;
            while (H.ticks_done < due && board.state == FW_RUNNING && H.n_rows < MAX_BLOCK) {
                fw_tick(&board);
                H.ticks_done++;
            }
            /* the stage in blocks of >= 10 ms of ticks: the helper's cost per call dominates small blocks */
            uint32_t flush_rows = H.rate / 100u > MAX_BLOCK / 2u ? MAX_BLOCK / 2u : H.rate / 100u;
            if (H.n_rows >= flush_rows || H.n_rows >= MAX_BLOCK || board.state != FW_RUNNING) run_stage_block(&H);
            H.stage_us = t;
        } else {
            run_stage_block(&H);
            idle_stage(&H, t);
        }
        if (H.to_stage) stage_collect(&H, board.state != FW_RUNNING && board.sens_ready != board.sens_head);
        fw_poll(&board, t);
        pty_write(&H);
        if (sig_unplug) {
            sig_unplug = 0;
            if (!replug_at) {
                char line[80];
                snprintf(line, sizeof line, "unplugged (SIGUSR1) for %g s", unplug_s);
                logline("WARNING", line);
                pty_close(&H);
                replug_at = t + (uint64_t)(unplug_s * 1e6) + 1u;
            }
        }
        if (replug_at && t >= replug_at) {
            replug_at = 0;
            pty_open(&H);
            char line[200];
            snprintf(line, sizeof line, "plugged in again: %s", H.link ? H.link : H.slave);
            logline("WARNING", line);
        }
    }
    logline("INFO", "stopping");
    pty_close(&H);
    return 0;
}
