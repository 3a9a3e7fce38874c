/* A TCG plugin for qemu-user that counts the guest instructions a process executes and prints
 * "guest_instructions: N" on stderr when it exits (benchmarks/pi_step_qemu.sh builds and uses it).
 *
 * Written against qemu 7.2's plugin API, version 1 (Debian 12's qemu-user); Debian ships neither
 * the plugin header nor the example plugins, so the few declarations it needs are spelt out here
 * (their signatures as in qemu 7.2's include/qemu/qemu-plugin.h). Each translated block adds its
 * instruction count to a counter whenever it runs (an inline add, no call). One counter for every
 * thread, not atomic: exact for a single-threaded program (run it with OPENBLAS_NUM_THREADS=1).
 * A block left midway by a fault would be counted whole; the measured Python code does not fault.
 *
 *   gcc -O2 -shared -fPIC -o libinsncount.so benchmarks/qemu_insn_count.c
 *   qemu-aarch64 -cpu cortex-a53 -plugin ./libinsncount.so -L ROOT ROOT/usr/bin/python3 ...
 */
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>

typedef uint64_t qemu_plugin_id_t;
typedef struct qemu_info_t qemu_info_t;
struct qemu_plugin_tb;
enum qemu_plugin_op { QEMU_PLUGIN_INLINE_ADD_U64 };
typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t id, struct qemu_plugin_tb *tb);
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t id, void *userdata);

void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id, qemu_plugin_vcpu_tb_trans_cb_t cb);
void qemu_plugin_register_vcpu_tb_exec_inline(struct qemu_plugin_tb *tb, enum qemu_plugin_op op,
                                              void *ptr, uint64_t imm);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, qemu_plugin_udata_cb_t cb, void *userdata);

__attribute__((visibility("default"))) int qemu_plugin_version = 1;

static uint64_t executed;

static void on_translate(qemu_plugin_id_t id, struct qemu_plugin_tb *tb)
{
    qemu_plugin_register_vcpu_tb_exec_inline(tb, QEMU_PLUGIN_INLINE_ADD_U64, &executed,
                                             qemu_plugin_tb_n_insns(tb));
}

static void on_exit(qemu_plugin_id_t id, void *userdata)
{
    fprintf(stderr, "guest_instructions: %llu\n", (unsigned long long)executed);
}

__attribute__((visibility("default")))
int qemu_plugin_install(qemu_plugin_id_t id, const qemu_info_t *info, int argc, char **argv)
{
    qemu_plugin_register_vcpu_tb_trans_cb(id, on_translate);
    qemu_plugin_register_atexit_cb(id, on_exit, NULL);
    return 0;
}
