/*
 * A qemu TCG plugin that counts the guest instructions a program executes, in all and per
 * function (the guest binary's symbol of each translated block's first instruction), written to
 * the plugin API of qemu 7.2 (Debian 12's qemu-user; API version 1). Used by
 * scripts/orin-estimate.sh to count instructions per tracked frame on aarch64.
 *
 * Build: gcc -shared -fPIC -O2 -o insn-count.so scripts/qemu-insn-count.c
 * Run:   qemu-aarch64 -plugin ./insn-count.so -d plugin -D count.txt PROGRAM ARGS...
 *        (`count.txt` then holds "instructions N", one "fn N SYMBOL" line per function, and one
 *        "tb VADDR INSNS EXECS SYMBOL" line per translated block that ran over 100000
 *        instructions: the hot blocks, for a pipeline model such as llvm-mca).
 *
 * Every execution of a translated block adds 1 to its counter atomically, so a program's threads
 * are all counted.
 *
 * Only the declarations this file uses are written here (the API is a stable C ABI); no qemu
 * header is needed to build it.
 */
#include <inttypes.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>

typedef uint64_t qemu_plugin_id_t;
struct qemu_plugin_tb;
typedef struct qemu_info_t qemu_info_t;
enum qemu_plugin_cb_flags { QEMU_PLUGIN_CB_NO_REGS };
typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t id, struct qemu_plugin_tb *tb);
typedef void (*qemu_plugin_vcpu_udata_cb_t)(unsigned int vcpu_index, void *userdata);
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t id, void *userdata);

void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id, qemu_plugin_vcpu_tb_trans_cb_t cb);
void qemu_plugin_register_vcpu_tb_exec_cb(struct qemu_plugin_tb *tb, qemu_plugin_vcpu_udata_cb_t cb,
                                          enum qemu_plugin_cb_flags flags, void *userdata);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
struct qemu_plugin_insn;
struct qemu_plugin_insn *qemu_plugin_tb_get_insn(const struct qemu_plugin_tb *tb, size_t idx);
const char *qemu_plugin_insn_symbol(const struct qemu_plugin_insn *insn);
uint64_t qemu_plugin_tb_vaddr(const struct qemu_plugin_tb *tb);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, qemu_plugin_udata_cb_t cb, void *userdata);
void qemu_plugin_outs(const char *string);

__attribute__((visibility("default"))) int qemu_plugin_version = 1;

/* One counter per translated block, keyed by its address and length (a block translated again
 * after a flush finds its slot); every execution adds 1 atomically, so threads of the guest
 * (tract's loader runs two) lose no counts. */
#define TB_SLOTS (1 << 20)
struct block {
    uint64_t vaddr;
    uint64_t insns;
    uint64_t execs;
    const char *sym;
};
static struct block blocks[TB_SLOTS];
static uint64_t lost; /* instructions of blocks that found no slot */

static struct block *block_of(uint64_t vaddr, uint64_t insns, const char *sym) {
    size_t h = (size_t)((vaddr >> 2) * 0x9E3779B97F4A7C15ull >> 44);
    for (size_t k = 0; k < TB_SLOTS; k++) {
        struct block *b = &blocks[(h + k) % TB_SLOTS];
        if (b->insns && b->vaddr == vaddr && b->insns == insns) return b;
        if (!b->insns) {
            b->vaddr = vaddr;
            b->insns = insns;
            b->sym = sym;
            return b;
        }
    }
    return NULL;
}

static void on_exec(unsigned int vcpu, void *userdata) {
    (void)vcpu;
    __atomic_fetch_add(&((struct block *)userdata)->execs, 1, __ATOMIC_RELAXED);
}

static void on_lost(unsigned int vcpu, void *userdata) {
    (void)vcpu;
    __atomic_fetch_add(&lost, (uint64_t)(uintptr_t)userdata, __ATOMIC_RELAXED);
}

static void on_translate(qemu_plugin_id_t id, struct qemu_plugin_tb *tb) {
    (void)id;
    size_t n = qemu_plugin_tb_n_insns(tb);
    if (!n) return;
    const char *sym = qemu_plugin_insn_symbol(qemu_plugin_tb_get_insn(tb, 0));
    struct block *b = block_of(qemu_plugin_tb_vaddr(tb), n, sym);
    if (b)
        qemu_plugin_register_vcpu_tb_exec_cb(tb, on_exec, QEMU_PLUGIN_CB_NO_REGS, b);
    else
        qemu_plugin_register_vcpu_tb_exec_cb(tb, on_lost, QEMU_PLUGIN_CB_NO_REGS, (void *)(uintptr_t)n);
}

/* Per-function sums at exit, keyed by the symbol's address. */
#define SLOTS 65536
static const char *names[SLOTS];
static uint64_t counts[SLOTS];

static uint64_t *counter_of(const char *sym) {
    static uint64_t other;
    if (!sym) return &other;
    size_t h = ((uintptr_t)sym >> 3) * 0x9E3779B97F4A7C15ull >> 48;
    for (size_t k = 0; k < SLOTS; k++) {
        size_t i = (h + k) % SLOTS;
        if (names[i] == sym) return &counts[i];
        if (!names[i]) {
            names[i] = sym;
            return &counts[i];
        }
    }
    return &other;
}

static void on_exit(qemu_plugin_id_t id, void *userdata) {
    (void)id;
    (void)userdata;
    char line[4096];
    uint64_t total = lost, other = lost;
    for (size_t i = 0; i < TB_SLOTS; i++) {
        struct block *b = &blocks[i];
        if (!b->insns) continue;
        total += b->insns * b->execs;
        if (b->sym)
            *counter_of(b->sym) += b->insns * b->execs;
        else
            other += b->insns * b->execs;
    }
    snprintf(line, sizeof line, "instructions %" PRIu64 "\n", total);
    qemu_plugin_outs(line);
    for (size_t i = 0; i < SLOTS; i++) {
        if (names[i] && counts[i]) {
            snprintf(line, sizeof line, "fn %" PRIu64 " %s\n", counts[i], names[i]);
            qemu_plugin_outs(line);
        }
    }
    snprintf(line, sizeof line, "fn %" PRIu64 " (other)\n", other);
    qemu_plugin_outs(line);
    for (size_t i = 0; i < TB_SLOTS; i++) {
        struct block *b = &blocks[i];
        if (b->insns && b->insns * b->execs > 100000) {
            snprintf(line, sizeof line, "tb %" PRIx64 " %" PRIu64 " %" PRIu64 " %s\n", b->vaddr, b->insns, b->execs,
                     b->sym ? b->sym : "(other)");
            qemu_plugin_outs(line);
        }
    }
}

__attribute__((visibility("default"))) int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info, int argc,
                                                              char **argv) {
    (void)info;
    (void)argc;
    (void)argv;
    qemu_plugin_register_vcpu_tb_trans_cb(id, on_translate);
    qemu_plugin_register_atexit_cb(id, on_exit, NULL);
    return 0;
}
