/* QEMU TCG plugin (API v1, QEMU 7.2) for onechip-qemu: logs every store to
 * the firmware's pin ports with the instruction count at which it ran, and
 * attributes instructions to the contexts the firmware marks (stepper
 * interrupt, heater interrupt, console interrupt, idle; the rest is thread
 * code).
 *
 * Usage: -plugin libpinlog.so,out=FILE[,trace=1]
 *
 * FILE gets one line per pin store, "<insns> <offset>" (offset from
 * PINS in hex: port * 0x1000 + 4 * (pin + 16 * level)), then at exit
 * "cpu <context> <insns> <runs> <longest run> <its start>" lines (in
 * instructions) and "total <insns>". With trace=1, every context change
 * too: "> <context> <insns>" on entry, "< <context> <insns>" on exit.
 * With -icount shift=1 and a guest that never sleeps, insns * 2 ns is
 * the virtual time.
 *
 * The declarations are a hand-written subset of include/qemu/qemu-plugin.h
 * (Debian does not ship the header), as in ../../shared/tools/m7count. */
#include <inttypes.h>
#include <stdio.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef uint64_t qemu_plugin_id_t;
typedef struct qemu_info_t qemu_info_t;
typedef uint32_t qemu_plugin_meminfo_t;
struct qemu_plugin_tb;
struct qemu_plugin_insn;
enum qemu_plugin_cb_flags { QEMU_PLUGIN_CB_NO_REGS, QEMU_PLUGIN_CB_R_REGS, QEMU_PLUGIN_CB_RW_REGS };
enum qemu_plugin_mem_rw { QEMU_PLUGIN_MEM_R = 1, QEMU_PLUGIN_MEM_W, QEMU_PLUGIN_MEM_RW };
enum qemu_plugin_op { QEMU_PLUGIN_INLINE_ADD_U64 };
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t id, void *userdata);
typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t id, struct qemu_plugin_tb *tb);
typedef void (*qemu_plugin_vcpu_mem_cb_t)(unsigned int vcpu_index, qemu_plugin_meminfo_t info,
                                          uint64_t vaddr, void *userdata);

void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id, qemu_plugin_vcpu_tb_trans_cb_t cb);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
struct qemu_plugin_insn *qemu_plugin_tb_get_insn(const struct qemu_plugin_tb *tb, size_t idx);
void qemu_plugin_register_vcpu_insn_exec_inline(struct qemu_plugin_insn *insn, enum qemu_plugin_op op,
                                                void *ptr, uint64_t imm);
void qemu_plugin_register_vcpu_mem_cb(struct qemu_plugin_insn *insn, qemu_plugin_vcpu_mem_cb_t cb,
                                      enum qemu_plugin_cb_flags flags, enum qemu_plugin_mem_rw rw,
                                      void *userdata);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, qemu_plugin_udata_cb_t cb, void *userdata);
void qemu_plugin_outs(const char *string);

__attribute__((visibility("default"))) int qemu_plugin_version = 1;

/* The firmware's addresses (qemu/src/machine.rs). */
#define PINS UINT64_C(0x40010000)
#define PROBE UINT64_C(0x4001F000)
#define REGION UINT64_C(0x10000)

enum { STEPPER, HEATERS, CONSOLE, IDLE, THREAD, CONTEXTS };
static const char *names[CONTEXTS] = {"stepper", "heaters", "console", "idle", "thread"};

static uint64_t total;              /* instructions so far (one vCPU) */
static FILE *out;
static int trace;                  /* trace=1: log every context change too */
static int stack[16];               /* contexts entered, innermost last */
static int depth;
static uint64_t since;              /* `total` at the last context change */
static uint64_t insns[CONTEXTS], runs[CONTEXTS], longest[CONTEXTS];
static uint64_t started[CONTEXTS];  /* `total` when each context was entered */
static uint64_t longest_at[CONTEXTS]; /* `total` when the longest run started */

static int current(void) { return depth ? stack[depth - 1] : THREAD; }

static void charge(void)
{
    insns[current()] += total - since;
    since = total;
}

static void on_store(unsigned int vcpu, qemu_plugin_meminfo_t info, uint64_t vaddr, void *u)
{
    (void)vcpu; (void)info; (void)u;
    if (vaddr < PINS || vaddr >= PINS + REGION) return;
    if (vaddr < PROBE) {
        fprintf(out, "%" PRIu64 " %" PRIx64 "\n", total, vaddr - PINS);
        return;
    }
    uint64_t code = (vaddr - PROBE) / 4;
    int context = (int)(code / 2);
    if (context >= THREAD) return;
    charge();
    if (trace) fprintf(out, "%c %s %" PRIu64 "\n", code % 2 ? '<' : '>', names[context], total);
    if (code % 2 == 0) {
        if (depth < 16) stack[depth++] = context;
        started[context] = total;
        runs[context]++;
    } else if (depth > 0 && stack[depth - 1] == context) {
        depth--;
        uint64_t run = total - started[context];
        if (run > longest[context]) { longest[context] = run; longest_at[context] = started[context]; }
    }
}

static void tb_trans(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    (void)id;
    size_t n = qemu_plugin_tb_n_insns(tb);
    for (size_t i = 0; i < n; i++) {
        struct qemu_plugin_insn *insn = qemu_plugin_tb_get_insn(tb, i);
        qemu_plugin_register_vcpu_insn_exec_inline(insn, QEMU_PLUGIN_INLINE_ADD_U64, &total, 1);
        qemu_plugin_register_vcpu_mem_cb(insn, on_store, QEMU_PLUGIN_CB_NO_REGS, QEMU_PLUGIN_MEM_W, NULL);
    }
}

static void at_exit(qemu_plugin_id_t id, void *u)
{
    (void)id; (void)u;
    charge();
    for (int c = 0; c < CONTEXTS; c++)
        fprintf(out, "cpu %s %" PRIu64 " %" PRIu64 " %" PRIu64 " %" PRIu64 "\n", names[c], insns[c], runs[c],
                longest[c], longest_at[c]);
    fprintf(out, "total %" PRIu64 "\n", total);
    fclose(out);
}

__attribute__((visibility("default")))
int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info, int argc, char **argv)
{
    (void)info;
    const char *path = NULL;
    for (int i = 0; i < argc; i++)
        if (!strncmp(argv[i], "out=", 4)) path = argv[i] + 4;
        else if (!strcmp(argv[i], "trace=1")) trace = 1;
    if (!path) { qemu_plugin_outs("pinlog: out=FILE is required\n"); return -1; }
    out = fopen(path, "w");
    if (!out) { qemu_plugin_outs("pinlog: cannot open out=FILE\n"); return -1; }
    setvbuf(out, NULL, _IOFBF, 1 << 20);
    qemu_plugin_register_vcpu_tb_trans_cb(id, tb_trans);
    qemu_plugin_register_atexit_cb(id, at_exit, NULL);
    return 0;
}
