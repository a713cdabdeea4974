/*
 * A stand-in for OpenHaptics' libHD.so, for tests only. Written for dmarionette from the
 * public function signatures of HD/hd.h and HD/hdScheduler.h and the constant values of
 * HD/hdDefines.h; it contains no vendor code.
 *
 * It emulates one device: a scheduler thread calls the scheduled callbacks at ~1 kHz,
 * hdGetDoublev(HD_CURRENT_TRANSFORM) reports a transform the test sets, forces set in a
 * frame are "sent to the motors" at hdEndFrame (only while HD_FORCE_OUTPUT is enabled)
 * and logged, and the test can make hdInitDevice fail or inject an error.
 *
 * Build: gcc -shared -fPIC -O2 -pthread fake_hd.c -o libHD.so
 */
#include <math.h>
#include <pthread.h>
#include <stddef.h>
#include <string.h>
#include <time.h>

typedef unsigned int HHD;
typedef unsigned int HDenum;
typedef unsigned int HDerror;
typedef unsigned int HDCallbackCode;
typedef unsigned long HDSchedulerHandle;
typedef unsigned short HDushort;
typedef HDCallbackCode (*HDSchedulerCallback)(void *);
typedef struct { HDerror errorCode; int internalErrorCode; HHD hHD; } HDErrorInfo;

#define HD_SUCCESS 0x0000
#define HD_INVALID_ENUM 0x0100
#define HD_INVALID_OPERATION 0x0102
#define HD_BAD_HANDLE 0x0104
#define HD_DEVICE_ALREADY_INITIATED 0x0301
#define HD_COMM_ERROR 0x0302
#define HD_ILLEGAL_BEGIN 0x0400
#define HD_ILLEGAL_END 0x0401
#define HD_SCHEDULER_FULL 0x0501
#define HD_CURRENT_BUTTONS 0x2000
#define HD_CURRENT_POSITION 0x2050
#define HD_CURRENT_TRANSFORM 0x2052
#define HD_USABLE_WORKSPACE_DIMENSIONS 0x2551
#define HD_CALIBRATION_STYLE 0x2555
#define HD_NOMINAL_MAX_FORCE 0x2603
#define HD_NOMINAL_MAX_CONTINUOUS_FORCE 0x2604
#define HD_CURRENT_FORCE 0x2700
#define HD_FORCE_OUTPUT 0x4000
#define HD_CALLBACK_DONE 0
#define HD_CALIBRATION_OK 0x5000
#define HD_CALIBRATION_NEEDS_UPDATE 0x5001
#define HD_INVALID_HANDLE 0xFFFFFFFFu

#define MAX_CALLBACKS 8
#define MAX_ERRORS 16
#define LOG_SIZE 65536

static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_t sched_thread;
static volatile int sched_running = 0;
static int initialized = 0;
static int force_enabled = 0;
static int in_frame = 0;
static HDErrorInfo errors[MAX_ERRORS];
static int error_count = 0;
static HDerror init_failure = HD_SUCCESS;

static HDSchedulerCallback callbacks[MAX_CALLBACKS];
static void *callback_data[MAX_CALLBACKS];
static long callback_count = 0;

static double transform[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
static int buttons = 0;
static double frame_force[3] = {0, 0, 0};
static double motor_force[3] = {0, 0, 0};
static double log_time[LOG_SIZE];
static double log_force[LOG_SIZE][3];
static long log_count = 0;

static HDenum calibration_status = HD_CALIBRATION_OK;
static int calibration_styles = 2; /* HD_CALIBRATION_AUTO */
static int calibration_updates = 0;
static int calibration_last_style = 0;

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

static void push_error(HDerror code, int internal) {
  if (error_count < MAX_ERRORS) {
    errors[error_count].errorCode = code;
    errors[error_count].internalErrorCode = internal;
    errors[error_count].hHD = initialized ? 0 : HD_INVALID_HANDLE;
    error_count++;
  }
}

/* ---- the HD API ---------------------------------------------------------------------- */

HHD hdInitDevice(const char *name) {
  pthread_mutex_lock(&lock);
  HHD h = 0;
  if (init_failure != HD_SUCCESS) {
    push_error(init_failure, -1);
    h = HD_INVALID_HANDLE;
  } else if (name != NULL && strcmp(name, "Default Device") != 0 && strcmp(name, "Fake Touch") != 0) {
    push_error(HD_BAD_HANDLE, -2);
    h = HD_INVALID_HANDLE;
  } else if (initialized) {
    push_error(HD_DEVICE_ALREADY_INITIATED, 0);
    h = HD_INVALID_HANDLE;
  } else {
    initialized = 1;
  }
  pthread_mutex_unlock(&lock);
  return h;
}

void hdDisableDevice(HHD h) {
  pthread_mutex_lock(&lock);
  if (h != 0 || !initialized) push_error(HD_BAD_HANDLE, 0);
  initialized = 0;
  force_enabled = 0;
  motor_force[0] = motor_force[1] = motor_force[2] = 0.0;
  pthread_mutex_unlock(&lock);
}

void hdMakeCurrentDevice(HHD h) {
  pthread_mutex_lock(&lock);
  if (h != 0 || !initialized) push_error(HD_BAD_HANDLE, 0);
  pthread_mutex_unlock(&lock);
}

HDErrorInfo hdGetError(void) {
  HDErrorInfo e = {HD_SUCCESS, 0, HD_INVALID_HANDLE};
  pthread_mutex_lock(&lock);
  if (error_count > 0) {
    e = errors[0];
    memmove(errors, errors + 1, (size_t)(error_count - 1) * sizeof(HDErrorInfo));
    error_count--;
  }
  pthread_mutex_unlock(&lock);
  return e;
}

const char *hdGetErrorString(HDerror code) {
  switch (code) {
    case HD_SUCCESS: return "No error";
    case HD_INVALID_ENUM: return "Invalid enumeration value";
    case HD_INVALID_OPERATION: return "Invalid operation";
    case HD_BAD_HANDLE: return "Invalid device handle";
    case HD_DEVICE_ALREADY_INITIATED: return "Device already initiated";
    case HD_COMM_ERROR: return "Communication error";
    case HD_ILLEGAL_BEGIN: return "Illegal begin frame";
    case HD_ILLEGAL_END: return "Illegal end frame";
    case HD_SCHEDULER_FULL: return "Scheduler full";
    default: return "Unknown error (fake libHD)";
  }
}

void hdEnable(HDenum cap) {
  pthread_mutex_lock(&lock);
  if (cap == HD_FORCE_OUTPUT) force_enabled = 1; else push_error(HD_INVALID_ENUM, 0);
  pthread_mutex_unlock(&lock);
}

void hdDisable(HDenum cap) {
  pthread_mutex_lock(&lock);
  if (cap == HD_FORCE_OUTPUT) force_enabled = 0; else push_error(HD_INVALID_ENUM, 0);
  pthread_mutex_unlock(&lock);
}

void hdBeginFrame(HHD h) {
  pthread_mutex_lock(&lock);
  if (h != 0 || !initialized) push_error(HD_BAD_HANDLE, 0);
  else if (in_frame) push_error(HD_ILLEGAL_BEGIN, 0);
  in_frame = 1;
  pthread_mutex_unlock(&lock);
}

void hdEndFrame(HHD h) {
  pthread_mutex_lock(&lock);
  if (!in_frame) push_error(HD_ILLEGAL_END, 0);
  in_frame = 0;
  for (int i = 0; i < 3; i++) motor_force[i] = force_enabled ? frame_force[i] : 0.0;
  if (log_count < LOG_SIZE) {
    log_time[log_count] = now_s();
    memcpy(log_force[log_count], motor_force, sizeof motor_force);
    log_count++;
  }
  (void)h;
  pthread_mutex_unlock(&lock);
}

void hdGetDoublev(HDenum p, double *v) {
  pthread_mutex_lock(&lock);
  switch (p) {
    case HD_CURRENT_TRANSFORM: memcpy(v, transform, sizeof transform); break;
    case HD_CURRENT_POSITION: v[0] = transform[12]; v[1] = transform[13]; v[2] = transform[14]; break;
    case HD_NOMINAL_MAX_FORCE: v[0] = 3.3; break;
    case HD_NOMINAL_MAX_CONTINUOUS_FORCE: v[0] = 0.88; break;
    case HD_USABLE_WORKSPACE_DIMENSIONS: {
      const double ws[6] = {-80, -60, -35, 80, 60, 35};
      memcpy(v, ws, sizeof ws);
      break;
    }
    case HD_CURRENT_FORCE: memcpy(v, motor_force, sizeof motor_force); break;
    default: push_error(HD_INVALID_ENUM, (int)p);
  }
  pthread_mutex_unlock(&lock);
}

void hdGetIntegerv(HDenum p, int *v) {
  pthread_mutex_lock(&lock);
  switch (p) {
    case HD_CURRENT_BUTTONS: v[0] = buttons; break;
    case HD_CALIBRATION_STYLE: v[0] = calibration_styles; break;
    default: push_error(HD_INVALID_ENUM, (int)p);
  }
  pthread_mutex_unlock(&lock);
}

void hdSetDoublev(HDenum p, const double *v) {
  pthread_mutex_lock(&lock);
  if (p == HD_CURRENT_FORCE && in_frame) memcpy(frame_force, v, sizeof frame_force);
  else push_error(p == HD_CURRENT_FORCE ? HD_INVALID_OPERATION : HD_INVALID_ENUM, (int)p);
  pthread_mutex_unlock(&lock);
}

HDenum hdCheckCalibration(void) {
  pthread_mutex_lock(&lock);
  HDenum s = calibration_status;
  pthread_mutex_unlock(&lock);
  return s;
}

void hdUpdateCalibration(HDenum style) {
  pthread_mutex_lock(&lock);
  calibration_updates++;
  calibration_last_style = (int)style;
  if (style & (unsigned)calibration_styles) calibration_status = HD_CALIBRATION_OK;
  else push_error(HD_INVALID_OPERATION, (int)style);
  pthread_mutex_unlock(&lock);
}

HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, HDushort priority) {
  (void)priority;
  pthread_mutex_lock(&lock);
  for (int i = 0; i < MAX_CALLBACKS; i++) {
    if (callbacks[i] == NULL) {
      callbacks[i] = cb;
      callback_data[i] = data;
      pthread_mutex_unlock(&lock);
      return (HDSchedulerHandle)(i + 1);
    }
  }
  push_error(HD_SCHEDULER_FULL, 0);
  pthread_mutex_unlock(&lock);
  return 0;
}

void hdUnschedule(HDSchedulerHandle h) {
  pthread_mutex_lock(&lock);
  if (h >= 1 && h <= MAX_CALLBACKS) callbacks[h - 1] = NULL;
  pthread_mutex_unlock(&lock);
}

static void *scheduler_main(void *arg) {
  (void)arg;
  struct timespec next;
  clock_gettime(CLOCK_MONOTONIC, &next);
  while (sched_running) {
    next.tv_nsec += 1000000;
    if (next.tv_nsec >= 1000000000) { next.tv_nsec -= 1000000000; next.tv_sec++; }
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
    for (int i = 0; i < MAX_CALLBACKS && sched_running; i++) {
      pthread_mutex_lock(&lock);
      HDSchedulerCallback cb = callbacks[i];
      void *data = callback_data[i];
      pthread_mutex_unlock(&lock);
      if (cb == NULL) continue;
      HDCallbackCode code = cb(data);  /* called without the lock: it calls back into hd* */
      pthread_mutex_lock(&lock);
      callback_count++;
      if (code == HD_CALLBACK_DONE) callbacks[i] = NULL;
      pthread_mutex_unlock(&lock);
    }
  }
  return NULL;
}

void hdStartScheduler(void) {
  if (sched_running) return;
  sched_running = 1;
  if (pthread_create(&sched_thread, NULL, scheduler_main, NULL) != 0) {
    sched_running = 0;
    pthread_mutex_lock(&lock);
    push_error(HD_INVALID_OPERATION, -3);
    pthread_mutex_unlock(&lock);
  }
}

void hdStopScheduler(void) {
  if (!sched_running) return;
  sched_running = 0;
  pthread_join(sched_thread, NULL);
}

/* ---- test controls (not part of the HD API) --------------------------------------------- */

void fake_hd_reset(void) {
  hdStopScheduler();
  pthread_mutex_lock(&lock);
  initialized = force_enabled = in_frame = 0;
  error_count = 0;
  init_failure = HD_SUCCESS;
  memset(callbacks, 0, sizeof callbacks);
  callback_count = 0;
  log_count = 0;
  buttons = 0;
  for (int i = 0; i < 16; i++) transform[i] = (i % 5 == 0) ? 1.0 : 0.0;
  memset(frame_force, 0, sizeof frame_force);
  memset(motor_force, 0, sizeof motor_force);
  calibration_status = HD_CALIBRATION_OK;
  calibration_styles = 2;
  calibration_updates = calibration_last_style = 0;
  pthread_mutex_unlock(&lock);
}

void fake_hd_set_transform(const double *m) {
  pthread_mutex_lock(&lock);
  memcpy(transform, m, sizeof transform);
  pthread_mutex_unlock(&lock);
}

void fake_hd_set_buttons(int b) {
  pthread_mutex_lock(&lock);
  buttons = b;
  pthread_mutex_unlock(&lock);
}

void fake_hd_set_init_failure(HDerror code) {
  pthread_mutex_lock(&lock);
  init_failure = code;
  pthread_mutex_unlock(&lock);
}

void fake_hd_inject_error(HDerror code, int internal) {
  pthread_mutex_lock(&lock);
  push_error(code, internal);
  pthread_mutex_unlock(&lock);
}

void fake_hd_set_calibration(HDenum status, int styles) {
  pthread_mutex_lock(&lock);
  calibration_status = status;
  calibration_styles = styles;
  pthread_mutex_unlock(&lock);
}

int fake_hd_calibration_updates(int *last_style) {
  pthread_mutex_lock(&lock);
  int n = calibration_updates;
  *last_style = calibration_last_style;
  pthread_mutex_unlock(&lock);
  return n;
}

/* Copies up to max logged motor forces (times [s, CLOCK_MONOTONIC], forces [N]); returns the count. */
long fake_hd_force_log(double *times, double *forces, long max) {
  pthread_mutex_lock(&lock);
  long n = log_count < max ? log_count : max;
  memcpy(times, log_time, (size_t)n * sizeof(double));
  memcpy(forces, log_force, (size_t)n * 3 * sizeof(double));
  pthread_mutex_unlock(&lock);
  return n;
}

long fake_hd_callback_count(void) {
  pthread_mutex_lock(&lock);
  long n = callback_count;
  pthread_mutex_unlock(&lock);
  return n;
}

int fake_hd_state(int *is_initialized, int *is_force_enabled, int *scheduler_running) {
  pthread_mutex_lock(&lock);
  *is_initialized = initialized;
  *is_force_enabled = force_enabled;
  *scheduler_running = sched_running;
  int n = 0;
  for (int i = 0; i < MAX_CALLBACKS; i++) n += callbacks[i] != NULL;
  pthread_mutex_unlock(&lock);
  return n;
}
