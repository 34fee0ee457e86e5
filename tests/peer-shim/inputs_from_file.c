// The Linux MCU peer's GPIO shim (../shared/peers/linux/fakegpio.c, used
// as it is) with inputs a test can change while the MCU runs: every
// input read returns the first byte of the file FAKEGPIO_IN_FILE as a
// digit ('0' or '1'), or FAKEGPIO_IN's value as before if that variable
// is not set. An output line's level when it is requested (its default
// value, which the shim does not log) is logged too, as a write, so that
// a pin set up on or off shows in the log. Build: cc -shared -fPIC -O2 -I <peers>/linux -o X.so
// inputs_from_file.c -ldl
#define ioctl fakegpio_ioctl
#include "fakegpio.c"
#undef ioctl

// The input file, opened at the first read (-1: not yet; -2: none).
static int input_fd = -1;

int ioctl(int fd, unsigned long req, ...)
{
    va_list ap;
    va_start(ap, req);
    void *arg = va_arg(ap, void *);
    va_end(ap);
    if (req == GPIO_GET_LINEHANDLE_IOCTL && fd >= 0 && fd < MAXFD
        && fd_kind[fd] == 1) {
        struct gpiohandle_request *r = arg;
        int ret = fakegpio_ioctl(fd, req, arg);
        if (ret == 0 && (r->flags & GPIOHANDLE_REQUEST_OUTPUT)) {
            struct gpiohandle_data d = { .values = { r->default_values[0] } };
            fakegpio_ioctl(r->fd, GPIOHANDLE_SET_LINE_VALUES_IOCTL, &d);
        }
        return ret;
    }
    if (req == GPIOHANDLE_GET_LINE_VALUES_IOCTL && fd >= 0 && fd < MAXFD
        && fd_kind[fd] == 2) {
        if (input_fd == -1) {
            const char *path = getenv("FAKEGPIO_IN_FILE");
            input_fd = path ? open(path, O_RDONLY | O_CLOEXEC) : -2;
            if (input_fd < 0)
                input_fd = -2;
        }
        char level;
        if (input_fd >= 0 && pread(input_fd, &level, 1, 0) == 1) {
            struct gpiohandle_data *d = arg;
            d->values[0] = level == '1';
            return 0;
        }
    }
    return fakegpio_ioctl(fd, req, arg);
}
