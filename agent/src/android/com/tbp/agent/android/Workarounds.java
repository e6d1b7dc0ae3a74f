package com.tbp.agent.android;

import android.app.Application;
import android.app.Instrumentation;
import android.content.Context;
import android.content.pm.ApplicationInfo;
import android.os.Build;
import java.lang.reflect.Constructor;
import java.lang.reflect.Field;
import java.lang.reflect.Method;

/**
 * What a process started by app_process lacks compared with an app, and CameraManager needs: an
 * ActivityThread (the framework's per-process state) marked as a system thread, an application
 * bound to the shell's package, and on Android 12+ its ConfigurationController. The approach is the
 * one scrcpy's server takes for its camera mirroring (Genymobile/scrcpy, Workarounds.java); the
 * fields are private framework ones, reached by reflection. Each step that fails is logged and the
 * agent goes on: the camera's own error then says what is missing.
 */
public final class Workarounds {

    private static Class<?> activityThreadClass;
    private static Object activityThread;

    private Workarounds() {
    }

    /** Sets the process up; call on the main thread after its Looper is prepared. */
    public static void apply() {
        try {
            activityThreadClass = Class.forName("android.app.ActivityThread");
            Constructor<?> constructor = activityThreadClass.getDeclaredConstructor();
            constructor.setAccessible(true);
            activityThread = constructor.newInstance();
            set(null, "sCurrentActivityThread", activityThread);
            Field systemThread = activityThreadClass.getDeclaredField("mSystemThread");
            systemThread.setAccessible(true);
            systemThread.setBoolean(activityThread, true);
        } catch (ReflectiveOperationException | RuntimeException e) {
            warn("no ActivityThread", e);
            return;
        }
        if (Build.VERSION.SDK_INT >= 31) {
            configurationController();
        }
        if (!"ONYX".equalsIgnoreCase(Build.BRAND)) {  // filling it breaks ONYX e-readers (scrcpy #5182)
            applicationInfo();
        }
        application();
    }

    /** The framework's system context, the base of {@link FakeContext}. */
    static Context systemContext() {
        try {
            Method method = activityThreadClass.getDeclaredMethod("getSystemContext");
            return (Context) method.invoke(activityThread);
        } catch (ReflectiveOperationException | RuntimeException e) {
            warn("no system context", e);
            return null;
        }
    }

    private static void configurationController() {
        try {
            Class<?> controllerClass = Class.forName("android.app.ConfigurationController");
            Class<?> internal = Class.forName("android.app.ActivityThreadInternal");
            Constructor<?> constructor = controllerClass.getDeclaredConstructor(internal);
            constructor.setAccessible(true);
            set(activityThread, "mConfigurationController", constructor.newInstance(activityThread));
        } catch (ReflectiveOperationException | RuntimeException e) {
            warn("no ConfigurationController", e);
        }
    }

    private static void applicationInfo() {
        try {
            Class<?> bindDataClass = Class.forName("android.app.ActivityThread$AppBindData");
            Constructor<?> constructor = bindDataClass.getDeclaredConstructor();
            constructor.setAccessible(true);
            Object bindData = constructor.newInstance();
            ApplicationInfo info = new ApplicationInfo();
            info.packageName = FakeContext.PACKAGE_NAME;
            Field appInfo = bindDataClass.getDeclaredField("appInfo");
            appInfo.setAccessible(true);
            appInfo.set(bindData, info);
            set(activityThread, "mBoundApplication", bindData);
        } catch (ReflectiveOperationException | RuntimeException e) {
            warn("no bound application", e);
        }
    }

    private static void application() {
        try {
            Application app = Instrumentation.newApplication(Application.class, FakeContext.get());
            set(activityThread, "mInitialApplication", app);
        } catch (ReflectiveOperationException | RuntimeException e) {
            warn("no application", e);
        }
    }

    private static void set(Object target, String name, Object value) throws ReflectiveOperationException {
        Field field = activityThreadClass.getDeclaredField(name);
        field.setAccessible(true);
        field.set(target, value);
    }

    private static void warn(String what, Throwable cause) {
        new LogcatLog().error("workaround: " + what, cause);
    }
}
